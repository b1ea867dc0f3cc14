//! Helpers shared by the serial tests: replaying the spec's `exchange replay` examples against a
//! board on a link.

use std::path::Path;
use std::time::{Duration, Instant};

use scanrig::devices::serial::link::Link;

/// One line from the board, without its terminator, within `deadline`.
fn read_line(link: &mut Link, deadline: Instant) -> String {
    let mut line = Vec::new();
    loop {
        match link.read_byte(deadline, "a line from the firmware", Duration::from_secs(5)) {
            Ok(b'\n') => return String::from_utf8_lossy(&line).into_owned(),
            Ok(b'\r') => {}
            Ok(b) => line.push(b),
            Err(e) => panic!("reading from the firmware: {e} (got so far: {:?})", String::from_utf8_lossy(&line)),
        }
    }
}

/// The `exchange replay` blocks of PROTOCOL.md: (first line, steps as (from host?, text)).
fn replay_blocks() -> Vec<(usize, Vec<(bool, String)>)> {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("firmware-protocol/PROTOCOL.md"))
        .expect("PROTOCOL.md is readable");
    let mut blocks = Vec::new();
    let mut current: Option<(usize, Vec<(bool, String)>)> = None;
    for (i, line) in text.lines().enumerate() {
        match (&mut current, line.trim_end()) {
            (None, "```exchange replay") => current = Some((i + 1, Vec::new())),
            (Some(_), "```") => blocks.extend(current.take()),
            (Some((_, steps)), l) => {
                if let Some(h) = l.strip_prefix("> ") {
                    steps.push((true, h.to_owned()));
                } else if let Some(b) = l.strip_prefix("< ") {
                    steps.push((false, b.to_owned()));
                }
            }
            (None, _) => {}
        }
    }
    blocks
}

/// Play every `exchange replay` block of PROTOCOL.md against the board on `link`: reset, then each
/// host line must get exactly the terminal reply shown and every event shown must arrive. Host lines
/// for which `skip(line)` is true are not sent (for boards whose identity differs from the spec's).
pub fn replay_spec_examples(link: &mut Link, board: &str, skip: impl Fn(&str) -> bool) {
    let blocks = replay_blocks();
    assert!(blocks.len() >= 4, "PROTOCOL.md has replayable examples");
    for (start_line, steps) in blocks {
        link.send(&[0x18]).expect("reset byte");
        let deadline = Instant::now() + Duration::from_secs(5);
        while !read_line(link, deadline).starts_with("@ready") {}
        let expected_events: Vec<&String> =
            steps.iter().filter(|(h, l)| !h && l.starts_with('@')).map(|(_, l)| l).collect();
        let mut seen_events = Vec::new();
        for (i, (from_host, text)) in steps.iter().enumerate() {
            if !from_host || skip(text) {
                continue;
            }
            let want = steps[i + 1..]
                .iter()
                .take_while(|(h, _)| !h)
                .find(|(_, l)| l.starts_with("ok") || l.starts_with("error:"))
                .map(|(_, l)| l.clone())
                .unwrap_or_else(|| panic!("PROTOCOL.md:{start_line}: `{text}` has no terminal reply"));
            link.send(format!("{text}\n").as_bytes()).expect("send");
            let deadline = Instant::now() + Duration::from_secs(5);
            let got = loop {
                let l = read_line(link, deadline);
                if l.starts_with('@') {
                    seen_events.push(l);
                } else {
                    break l;
                }
            };
            assert_eq!(got, want, "PROTOCOL.md:{start_line}: {board}'s reply to `{text}`");
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        while !expected_events.iter().all(|e| seen_events.contains(e)) {
            seen_events.push(read_line(link, deadline));
        }
    }
}
