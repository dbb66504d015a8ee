//! Arbitrary bytes through the serial-line photodiode's parser, in chunks. Nothing may panic;
//! no line is held past its `\n` (a complete line always yields one result); every line it
//! accepts re-encodes to bytes that parse to the same line; a good line after any garbage
//! is read.
//!
//! Input: `[chunk size byte][stream]`.
#![no_main]

use dioptra_photodiode::protocol::{parse_line, Line, LineParser, MAX_LINE_LEN};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, stream)) = data.split_first() else {
        return;
    };
    let mut parser = LineParser::new();
    for part in stream.chunks(usize::from(chunk) + 1) {
        for line in parser.push(part).into_iter().flatten() {
            let text = line.encode();
            assert!(text.len() <= MAX_LINE_LEN, "{line:?} re-encodes too long");
            let again = parse_line(text.trim_end_matches('\n').as_bytes());
            assert_eq!(again.as_ref(), Ok(&line));
        }
    }
    let after = parser.push(b"\n12,1\n");
    assert_eq!(
        after.last(),
        Some(&Ok(Line::Edge {
            device_time_us: 12,
            on: true
        }))
    );
});
