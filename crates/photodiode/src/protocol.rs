//! The serial-line photodiode's line protocol (firmware-protocol/photodiode/README.md), parsed
//! into typed lines. No I/O; the parser takes any bytes and yields a line or an error per line,
//! never panics, and never holds more than one line.

use crate::ids::HELLO_NAME;

/// Longest line, its `\n` included. A longer one is an error and is skipped to its end.
pub const MAX_LINE_LEN: usize = 64;
/// Longest free text in a hello line, bytes.
pub const MAX_ABOUT_LEN: usize = 40;

/// What the host sends: one command per line.
pub mod command {
    /// Asks for the hello line.
    pub const HELLO: &[u8] = b"v\n";
    /// Clock-sync ping: the device answers `s,<t_us>` with its clock when the `s` arrived.
    pub const SYNC: &[u8] = b"s\n";
}

/// One line from the device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Line {
    /// `dioptra-photodiode,<version>,<about>`: at start-up and in reply to `v`.
    Hello { version: u32, about: String },
    /// `<t_us>,<level>`: the comparator's output changed at device time `t_us`; `on` is the
    /// output after the edge (`1`: the light came on).
    Edge { device_time_us: u64, on: bool },
    /// `s,<t_us>`: the reply to a sync ping, the device clock when the ping arrived.
    Sync { device_time_us: u64 },
    /// `!overflow,<n>`: `n` edges were not reported (the device's queue was full).
    Overflow { lost: u64 },
    /// `#<text>`: for logs.
    Comment(String),
}

impl Line {
    /// The line as the device sends it, `\n` included.
    pub fn encode(&self) -> String {
        match self {
            Line::Hello { version, about } => format!("{HELLO_NAME},{version},{about}\n"),
            Line::Edge { device_time_us, on } => format!("{device_time_us},{}\n", u8::from(*on)),
            Line::Sync { device_time_us } => format!("s,{device_time_us}\n"),
            Line::Overflow { lost } => format!("!overflow,{lost}\n"),
            Line::Comment(text) => format!("#{text}\n"),
        }
    }
}

/// Why a line was not used. The parser has already moved on to the next line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    #[error("a line longer than {MAX_LINE_LEN} bytes, skipped to its end")]
    TooLong,
    #[error("a line with bytes that are not printable ASCII: {0:?}")]
    NotText(String),
    #[error("an unknown line {0:?}")]
    Unknown(String),
    #[error("a malformed {what} line {line:?}: {why}")]
    Malformed {
        what: &'static str,
        line: String,
        why: &'static str,
    },
}

/// Splits a byte stream into lines and parses each.
#[derive(Debug, Default, Clone)]
pub struct LineParser {
    line: Vec<u8>,
    /// Inside a line that was too long: drop bytes up to its `\n`.
    skipping: bool,
}

impl LineParser {
    pub fn new() -> Self {
        LineParser {
            line: Vec::with_capacity(MAX_LINE_LEN),
            skipping: false,
        }
    }

    /// Forgets a partial line (after a timeout or a reconnect).
    pub fn reset(&mut self) {
        self.line.clear();
        self.skipping = false;
    }

    /// Takes `bytes` and returns what every line they complete holds. Empty lines are skipped.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Result<Line, LineError>> {
        let mut out = Vec::new();
        for &b in bytes {
            if b == b'\n' {
                if !std::mem::take(&mut self.skipping) && !self.line.is_empty() {
                    out.push(parse_line(&self.line));
                }
                self.line.clear();
            } else if !self.skipping {
                if self.line.len() + 1 >= MAX_LINE_LEN {
                    out.push(Err(LineError::TooLong));
                    self.line.clear();
                    self.skipping = true;
                } else {
                    self.line.push(b);
                }
            }
        }
        out
    }
}

/// Parses one line, without its `\n` (a `\r` before it is dropped). An empty line is
/// [`LineError::Unknown`]; [`LineParser`] skips those before they get here.
pub fn parse_line(raw: &[u8]) -> Result<Line, LineError> {
    let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
    if raw.len() + 1 > MAX_LINE_LEN {
        return Err(LineError::TooLong);
    }
    if !raw.iter().all(|b| (0x20..=0x7E).contains(b)) {
        return Err(LineError::NotText(
            String::from_utf8_lossy(raw).into_owned(),
        ));
    }
    // Printable ASCII is UTF-8.
    let text = std::str::from_utf8(raw).unwrap_or_default();
    let malformed = |what, why| LineError::Malformed {
        what,
        line: text.to_string(),
        why,
    };
    if let Some(comment) = text.strip_prefix('#') {
        return Ok(Line::Comment(comment.to_string()));
    }
    if let Some(rest) = text.strip_prefix("!overflow,") {
        return match number(rest) {
            Some(lost) if lost > 0 => Ok(Line::Overflow { lost }),
            Some(_) => Err(malformed("overflow", "the count must be at least 1")),
            None => Err(malformed("overflow", "the count is not a decimal number")),
        };
    }
    if let Some(rest) = text.strip_prefix("s,") {
        return number(rest)
            .map(|device_time_us| Line::Sync { device_time_us })
            .ok_or_else(|| malformed("sync", "the time is not a decimal number of µs"));
    }
    if let Some(rest) = text
        .strip_prefix(HELLO_NAME)
        .and_then(|r| r.strip_prefix(','))
    {
        let (version, about) = rest.split_once(',').unwrap_or((rest, ""));
        let version = number(version)
            .and_then(|v| u32::try_from(v).ok())
            .ok_or_else(|| malformed("hello", "the version is not a decimal number"))?;
        if about.len() > MAX_ABOUT_LEN {
            return Err(malformed(
                "hello",
                "the text after the version is over 40 bytes",
            ));
        }
        return Ok(Line::Hello {
            version,
            about: about.to_string(),
        });
    }
    if text.starts_with(|c: char| c.is_ascii_digit()) {
        let Some((t, level)) = text.split_once(',') else {
            return Err(malformed("edge", "expected <t_us>,<level>"));
        };
        let device_time_us =
            number(t).ok_or_else(|| malformed("edge", "the time is not a decimal number of µs"))?;
        let on = match level {
            "1" => true,
            "0" => false,
            _ => return Err(malformed("edge", "the level is not 0 or 1")),
        };
        return Ok(Line::Edge { device_time_us, on });
    }
    Err(LineError::Unknown(text.to_string()))
}

/// A decimal u64: digits only (no sign, no spaces), at most 20 of them, no overflow.
fn number(field: &str) -> Option<u64> {
    if field.is_empty() || field.len() > 20 || !field.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    field.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn parse_all(bytes: &[u8]) -> Vec<Result<Line, LineError>> {
        LineParser::new().push(bytes)
    }

    #[test]
    fn every_line_kind_parses() {
        let got = parse_all(
            b"dioptra-photodiode,1,uno r3 bpw34 lm393\r\n12345678,1\n12349999,0\ns,12350000\n\
              !overflow,3\n#threshold pot at 40%\n\n",
        );
        assert_eq!(
            got,
            [
                Ok(Line::Hello {
                    version: 1,
                    about: "uno r3 bpw34 lm393".into()
                }),
                Ok(Line::Edge {
                    device_time_us: 12_345_678,
                    on: true
                }),
                Ok(Line::Edge {
                    device_time_us: 12_349_999,
                    on: false
                }),
                Ok(Line::Sync {
                    device_time_us: 12_350_000
                }),
                Ok(Line::Overflow { lost: 3 }),
                Ok(Line::Comment("threshold pot at 40%".into())),
            ]
        );
        // A hello without text, and one whose text has commas.
        assert_eq!(
            parse_line(b"dioptra-photodiode,2"),
            Ok(Line::Hello {
                version: 2,
                about: String::new()
            })
        );
        assert_eq!(
            parse_line(b"dioptra-photodiode,1,a,b"),
            Ok(Line::Hello {
                version: 1,
                about: "a,b".into()
            })
        );
        assert_eq!(
            parse_line(b"18446744073709551615,1"),
            Ok(Line::Edge {
                device_time_us: u64::MAX,
                on: true
            })
        );
    }

    #[test]
    fn malformed_lines_are_errors_that_name_the_line() {
        for bad in [
            &b"123,2"[..],
            b"123",
            b"123,1,7",
            b"18446744073709551616,1",
            b"1 23,1",
            b"s,",
            b"s,-5",
            b"s,+5",
            b"!overflow,0",
            b"!overflow,x",
            b"dioptra-photodiode,v1,x",
        ] {
            assert!(
                matches!(parse_line(bad), Err(LineError::Malformed { .. })),
                "{:?} gave {:?}",
                String::from_utf8_lossy(bad),
                parse_line(bad)
            );
        }
        assert!(matches!(
            parse_line(b"dioptra-photodiode,1,0123456789012345678901234567890123456789X"),
            Err(LineError::Malformed { what: "hello", .. })
        ));
        assert_eq!(
            parse_line(b"hello"),
            Err(LineError::Unknown("hello".into()))
        );
        assert_eq!(
            parse_line(b"!reset"),
            Err(LineError::Unknown("!reset".into()))
        );
        assert!(matches!(
            parse_line(b"12\x00,1"),
            Err(LineError::NotText(_))
        ));
        assert!(matches!(
            parse_line("12é,1".as_bytes()),
            Err(LineError::NotText(_))
        ));
    }

    #[test]
    fn a_long_line_is_one_error_and_the_next_line_is_read() {
        let mut bytes = vec![b'7'; 200];
        bytes.extend_from_slice(b",1\n55,0\n");
        assert_eq!(
            parse_all(&bytes),
            [
                Err(LineError::TooLong),
                Ok(Line::Edge {
                    device_time_us: 55,
                    on: false
                })
            ]
        );
        // 63 bytes and its newline fit; 64 do not.
        let fits = format!("#{}\n", "x".repeat(62));
        assert_eq!(fits.len(), MAX_LINE_LEN);
        assert!(matches!(
            parse_all(fits.as_bytes())[..],
            [Ok(Line::Comment(_))]
        ));
        let over = format!("#{}\n", "x".repeat(63));
        assert_eq!(parse_all(over.as_bytes()), [Err(LineError::TooLong)]);
    }

    fn any_line() -> impl Strategy<Value = Line> {
        prop_oneof![
            (0..1000u32, "[ -~]{0,40}").prop_map(|(version, about)| Line::Hello { version, about }),
            (any::<u64>(), any::<bool>())
                .prop_map(|(device_time_us, on)| Line::Edge { device_time_us, on }),
            any::<u64>().prop_map(|device_time_us| Line::Sync { device_time_us }),
            (1..u64::MAX).prop_map(|lost| Line::Overflow { lost }),
            "[ -~]{0,60}".prop_map(Line::Comment),
        ]
    }

    proptest! {
        #[test]
        fn lines_round_trip_in_any_chunking(
            lines in prop::collection::vec(any_line(), 1..20),
            chunk in 1usize..70,
        ) {
            let bytes: Vec<u8> = lines.iter().flat_map(|l| l.encode().into_bytes()).collect();
            let mut parser = LineParser::new();
            let got: Vec<_> = bytes.chunks(chunk).flat_map(|c| parser.push(c)).collect();
            let want: Vec<_> = lines.into_iter().map(Ok).collect();
            prop_assert_eq!(got, want);
        }

        #[test]
        fn garbage_never_panics_and_the_stream_recovers(garbage in prop::collection::vec(any::<u8>(), 0..300)) {
            let mut parser = LineParser::new();
            let _ = parser.push(&garbage);
            let got = parser.push(b"\n42,1\n");
            prop_assert_eq!(got.last(), Some(&Ok(Line::Edge { device_time_us: 42, on: true })));
        }
    }
}
