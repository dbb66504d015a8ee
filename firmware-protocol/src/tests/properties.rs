//! Property tests over arbitrary messages, chunkings, garbage and corruption.

use std::vec::Vec;

use proptest::prelude::*;

use super::wire;
use crate::test_support::any_message;
use crate::*;

fn frames() -> impl Strategy<Value = Vec<Frame>> {
    prop::collection::vec(
        (any::<u16>(), any_message()).prop_map(|(request_id, message)| Frame {
            version: PROTOCOL_VERSION,
            request_id,
            message,
        }),
        1..6,
    )
}

proptest! {
    #[test]
    fn any_message_round_trips(request_id in any::<u16>(), message in any_message()) {
        let bytes = wire(request_id, &message);
        let expected = Frame { version: PROTOCOL_VERSION, request_id, message };
        prop_assert_eq!(decode_frame(&bytes), Ok(expected.clone()));
        let streamed: Vec<_> = FrameDecoder::new().push(&bytes).collect();
        prop_assert_eq!(streamed, [Ok(expected)]);
    }

    #[test]
    fn any_chunking_yields_the_same_frames(
        frames in frames(),
        chunk_sizes in prop::collection::vec(1usize..40, 1..64),
    ) {
        let bytes: Vec<u8> = frames.iter().flat_map(|f| wire(f.request_id, &f.message)).collect();
        let mut decoder = FrameDecoder::new();
        let mut decoded = Vec::new();
        let mut rest = &bytes[..];
        for size in chunk_sizes.iter().cycle() {
            if rest.is_empty() {
                break;
            }
            let (chunk, tail) = rest.split_at((*size).min(rest.len()));
            decoded.extend(decoder.push(chunk));
            rest = tail;
        }
        let expected: Vec<_> = frames.into_iter().map(Ok).collect();
        prop_assert_eq!(decoded, expected);
    }

    #[test]
    fn garbage_never_panics_and_a_following_frame_decodes(
        garbage in prop::collection::vec(any::<u8>(), 0..1200),
        request_id in any::<u16>(),
        message in any_message(),
    ) {
        let _ = decode_frame(&garbage);
        let mut decoder = FrameDecoder::new();
        for _ in decoder.push(&garbage) {}
        // A sender flushes with a 0x00 before its frame; the garbage's tail ends there.
        let mut bytes = std::vec![0];
        bytes.extend(wire(request_id, &message));
        let results: Vec<_> = decoder.push(&bytes).collect();
        let expected = Frame { version: PROTOCOL_VERSION, request_id, message };
        prop_assert_eq!(results.last(), Some(&Ok(expected)));
    }

    #[test]
    fn any_single_corrupted_byte_gives_an_error_not_a_message(
        request_id in any::<u16>(),
        message in any_message(),
        position in any::<prop::sample::Index>(),
        flip in 1u8..=255,
    ) {
        let mut bytes = wire(request_id, &message);
        let at = position.index(bytes.len());
        bytes[at] ^= flip;
        prop_assert!(decode_frame(&bytes).is_err());
        // Through the stream, with a delimiter after in case the corruption hit the original one.
        bytes.push(0);
        let results: Vec<_> = FrameDecoder::new().push(&bytes).collect();
        prop_assert!(!results.is_empty());
        prop_assert!(results.iter().all(Result::is_err), "{:?}", results);
    }
}
