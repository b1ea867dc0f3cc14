//! Property tests: no byte sequence makes a decoder panic, and one newline always brings it back in
//! step.

use firmware_protocol::{
    BoardDecoder, BoardMessage, Command, CommandDecoder, Framing, Input, Millideg, OkPayload, MAX_LINE,
};
use proptest::prelude::*;

fn drain_board(d: &mut BoardDecoder, bytes: &[u8]) -> usize {
    let mut lines = 0;
    let mut rest = bytes;
    while !rest.is_empty() {
        let (used, out) = d.decode(rest);
        assert!(used > 0 && used <= rest.len());
        rest = &rest[used..];
        lines += usize::from(out.is_some());
    }
    lines
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn board_decoder_never_panics_and_resyncs(garbage in proptest::collection::vec(any::<u8>(), 0..400)) {
        let mut d = BoardDecoder::new();
        drain_board(&mut d, &garbage);
        // After garbage, a newline then a valid line decodes exactly.
        let mut got = Vec::new();
        for &b in b"\nok N5 pos=12 moving=1\n" {
            if let Some(r) = d.push(b) {
                got.push(r);
            }
        }
        let last = got.pop().expect("the valid line completes");
        prop_assert_eq!(
            last,
            Ok((Framing { line: Some(5), checksum: false },
                BoardMessage::Ok { line: Some(5), payload: OkPayload::Position { steps: 12, moving: true } }))
        );
    }

    #[test]
    fn command_decoder_never_panics_and_resyncs(garbage in proptest::collection::vec(any::<u8>(), 0..400)) {
        let mut d = CommandDecoder::new();
        for &b in &garbage {
            let _ = d.push(b);
        }
        let mut last = None;
        for &b in b"\nN9 MOVE -12.5*00\nN9 MOVE -12.5\n" {
            if let Some(i) = d.push(b) {
                last = Some(i);
            }
        }
        prop_assert_eq!(
            last,
            Some(Input::Line(Ok((Framing { line: Some(9), checksum: false }, Command::Move(Millideg(-12_500))))))
        );
    }

    #[test]
    fn printable_lines_never_panic(line in "[ -~]{0,120}") {
        let _ = BoardMessage::decode(line.as_bytes());
        let _ = Command::decode(line.as_bytes());
    }

    #[test]
    fn commands_round_trip(
        which in 0u8..13, a in any::<i32>(), b in any::<u8>(), c in any::<u16>(), d in any::<u32>(),
        line in proptest::option::of(any::<u16>()), checksum in any::<bool>(),
    ) {
        let angle = Millideg(a % 1_000_000_000);
        let cmd = match which {
            0 => Command::Id,
            1 => Command::Caps,
            2 => Command::Pos,
            3 => Command::Move(angle),
            4 => Command::Turn(angle),
            5 => Command::Home,
            6 => Command::Zero,
            7 => Command::Motor(b % 2 == 1),
            8 => Command::Light { index: b, level: (c % 256) as u8 },
            9 => Command::Laser { index: b, on: c % 2 == 1 },
            10 => Command::Trigger { ms: c % 1000 + 1 },
            11 => Command::Safety { laser_s: c, idle_ms: d, watchdog_ms: d / 3 },
            _ => Command::Off,
        };
        let framing = Framing { line, checksum };
        let bytes = cmd.to_line(framing).expect("every command fits a line");
        prop_assert!(bytes.len() <= MAX_LINE + 1);
        let decoded = Command::decode(&bytes[..bytes.len() - 1]);
        prop_assert_eq!(decoded, Ok((framing, cmd)));
    }

    #[test]
    fn one_flipped_bit_in_a_checksummed_line_is_caught(bit in 0usize..(8 * 22)) {
        let mut bytes = Command::Move(Millideg(123_456)).to_line(Framing { line: Some(77), checksum: true })
            .expect("fits");
        let n = bytes.len() - 1;
        let (byte, shift) = (bit / 8 % n, bit % 8);
        bytes[byte] ^= 1 << shift;
        // A flip that turns a byte into a newline splits the line; everything else must be rejected
        // or (never) decode to the same command.
        let decoded = Command::decode(&bytes[..n]);
        prop_assert!(decoded.is_err(), "flip at byte {} bit {} went unnoticed: {:?}", byte, shift, decoded);
    }
}

#[test]
fn overlong_line_is_reported_once_then_decoder_recovers() {
    let mut d = BoardDecoder::new();
    let mut long = vec![b'x'; MAX_LINE + 10];
    long.extend_from_slice(b"\nok\n");
    let mut out = Vec::new();
    for b in long {
        if let Some(r) = d.push(b) {
            out.push(r);
        }
    }
    assert_eq!(out.len(), 2);
    assert_eq!(out[0], Err(firmware_protocol::DecodeError::Overflow));
    assert!(matches!(out[1], Ok((_, BoardMessage::Ok { line: None, payload: OkPayload::Empty }))));
}

#[test]
fn realtime_bytes_inside_a_line_do_not_break_it() {
    let mut d = CommandDecoder::new();
    let mut out = Vec::new();
    for &b in b"LIG?HT 1 2!00\n" {
        if let Some(i) = d.push(b) {
            out.push(i);
        }
    }
    assert_eq!(
        out,
        vec![
            Input::RealTime(b'?'),
            Input::RealTime(b'!'),
            Input::Line(Ok((Framing::PLAIN, Command::Light { index: 1, level: 200 })))
        ]
    );
}

#[test]
fn millidegrees_parse_and_print_canonically() {
    for (text, value) in [("0", 0), ("45", 45_000), ("-7.5", -7_500), ("0.125", 125), ("-0.001", -1), ("360", 360_000)]
    {
        assert_eq!(Millideg::parse(text.as_bytes()), Some(Millideg(value)), "{text}");
        assert_eq!(Millideg(value).to_string(), text);
    }
    for bad in ["", "-", "1.", ".5", "1.2345", "1e3", "--1", "1000001", "١"] {
        assert_eq!(Millideg::parse(bad.as_bytes()), None, "{bad:?}");
    }
    assert_eq!(Millideg::from_degrees(12.3456), Some(Millideg(12_346)));
    assert_eq!(Millideg::from_degrees(f64::NAN), None);
}

#[test]
fn rejected_lines_keep_a_trustworthy_line_number() {
    let mut d = CommandDecoder::new();
    let mut out = Vec::new();
    for &b in b"N5 LIGHT 0\nN6 FLY*00\nN7 FLY\n" {
        if let Some(i) = d.push(b) {
            out.push(i);
        }
    }
    use firmware_protocol::{DecodeError, Rejected};
    assert_eq!(
        out,
        vec![
            Input::Line(Err(Rejected { line: Some(5), error: DecodeError::BadArgument })),
            Input::Line(Err(Rejected { line: None, error: DecodeError::Checksum { computed: 0x0B, carried: 0 } })),
            Input::Line(Err(Rejected { line: Some(7), error: DecodeError::Unknown })),
        ]
    );
}
