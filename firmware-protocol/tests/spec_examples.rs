//! Every `exchange` block in PROTOCOL.md decodes and re-encodes to the same bytes, and follows the
//! one-terminal-reply-per-line rule, so the spec and the codec cannot drift apart.

use firmware_protocol::{realtime, BoardMessage, Command, ErrorCode};

#[derive(Debug)]
enum Step {
    Host(String),
    Board(String),
    RealTime(u8),
}

fn exchanges() -> Vec<(usize, Vec<Step>)> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/PROTOCOL.md");
    let text = std::fs::read_to_string(path).expect("PROTOCOL.md is readable");
    let mut blocks = Vec::new();
    let mut current: Option<(usize, Vec<Step>)> = None;
    for (i, line) in text.lines().enumerate() {
        let lineno = i + 1;
        match (&mut current, line.trim_end()) {
            (None, l) if l.starts_with("```exchange") => current = Some((lineno, Vec::new())),
            (Some(_), "```") => blocks.push(current.take().expect("inside a block")),
            (Some((_, steps)), l) => {
                let step = if let Some(rest) = l.strip_prefix("> ") {
                    Step::Host(rest.to_owned())
                } else if let Some(rest) = l.strip_prefix("< ") {
                    Step::Board(rest.to_owned())
                } else if let Some(rest) = l.strip_prefix("! ") {
                    Step::RealTime(match rest {
                        "?" => realtime::STATUS,
                        "!" => realtime::STOP,
                        "^X" => realtime::RESET,
                        other => panic!("PROTOCOL.md:{lineno}: unknown real-time byte {other:?}"),
                    })
                } else {
                    panic!("PROTOCOL.md:{lineno}: line in an exchange block must start with `> `, `< ` or `! `: {l:?}")
                };
                steps.push(step);
            }
            (None, _) => {}
        }
    }
    assert!(current.is_none(), "unterminated exchange block");
    blocks
}

#[test]
fn spec_has_examples_of_every_kind() {
    let blocks = exchanges();
    assert!(blocks.len() >= 8, "expected the spec's example blocks, found {}", blocks.len());
    let all: Vec<&Step> = blocks.iter().flat_map(|(_, s)| s).collect();
    assert!(all.iter().any(|s| matches!(s, Step::RealTime(_))));
    assert!(all.iter().any(|s| matches!(s, Step::Host(h) if h.contains('*'))));
}

#[test]
fn every_spec_example_round_trips() {
    for (start, steps) in exchanges() {
        // The error code a deliberately broken host line must get, if the last host line was one.
        let mut expected_error: Option<ErrorCode> = None;
        let mut replies_owed = 0usize;
        for step in &steps {
            match step {
                Step::Host(h) => {
                    assert_eq!(replies_owed, 0, "block at line {start}: `{h}` sent before the previous line's reply");
                    replies_owed = 1;
                    expected_error = None;
                    match Command::decode(h.as_bytes()) {
                        Ok((framing, cmd)) => {
                            let line = cmd.to_line(framing).expect("encodes");
                            assert_eq!(line, format!("{h}\n").into_bytes(), "block at line {start}: host line `{h}`");
                        }
                        Err(e) => expected_error = Some(e.error_code()),
                    }
                }
                Step::Board(b) => {
                    let (framing, msg) = BoardMessage::decode(b.as_bytes())
                        .unwrap_or_else(|e| panic!("block at line {start}: board line `{b}` does not decode: {e}"));
                    let line = msg.to_line(framing.checksum).expect("encodes");
                    assert_eq!(line, format!("{b}\n").into_bytes(), "block at line {start}: board line `{b}`");
                    if msg.is_terminal() {
                        assert_eq!(replies_owed, 1, "block at line {start}: `{b}` is a second terminal reply");
                        replies_owed = 0;
                        if let Some(code) = expected_error.take() {
                            match msg {
                                BoardMessage::Error { code: got, .. } => {
                                    assert_eq!(got, code, "block at line {start}: `{b}` names the wrong error")
                                }
                                other => panic!("block at line {start}: a broken line was answered {other:?}"),
                            }
                        }
                    }
                }
                Step::RealTime(b) => assert!(realtime::is_realtime(*b)),
            }
        }
        assert_eq!(replies_owed, 0, "block at line {start}: the last host line has no reply");
    }
}
