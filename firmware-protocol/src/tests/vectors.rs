//! Golden wire bytes for every message variant, stored in vectors/vectors.txt.
//!
//! The stored file is the truth: encoding must reproduce it byte for byte and decoding it must
//! give back the example messages. `DIOPTRA_BLESS=1 cargo test -p dioptra-protocol vectors`
//! rewrites it from the examples; review the diff before committing it.

use std::fmt::Write as _;
use std::string::String;
use std::vec::Vec;

use super::wire;
use crate::message::MESSAGE_VARIANT_COUNT;
use crate::test_support::examples;
use crate::{decode_frame, Frame, Message, PROTOCOL_VERSION};

const VECTORS_PATH: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/vectors/vectors.txt");

/// The variant's name, as Debug prints it before any fields.
fn variant_name(message: &Message) -> String {
    std::format!("{message:?}")
        .chars()
        .take_while(char::is_ascii_alphanumeric)
        .collect()
}

fn render() -> String {
    let mut text = std::format!(
        "# dioptra-protocol golden frames, protocol version {PROTOCOL_VERSION}. See PROTOCOL.md.\n\
         # One line per message: <variant> <request id> <wire bytes in hex, 0x00 delimiter included>\n"
    );
    for (request_id, message) in examples() {
        let bytes = hex::encode(wire(request_id, &message));
        writeln!(text, "{} {request_id} {bytes}", variant_name(&message)).expect("String write");
    }
    text
}

struct Vector {
    name: String,
    request_id: u16,
    bytes: Vec<u8>,
}

fn parse(text: &str) -> Vec<Vector> {
    text.lines()
        .filter(|line| !line.starts_with('#') && !line.trim().is_empty())
        .map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [name, request_id, bytes] = fields[..] else {
                panic!("vector line {line:?} does not have 3 fields");
            };
            Vector {
                name: name.into(),
                request_id: request_id.parse().expect("request id is a u16"),
                bytes: hex::decode(bytes).expect("wire bytes are hex"),
            }
        })
        .collect()
}

#[test]
fn golden_vectors_encode_and_decode_exactly() {
    if std::env::var_os("DIOPTRA_BLESS").is_some_and(|v| v == "1") {
        std::fs::write(VECTORS_PATH, render()).expect("write vectors/vectors.txt");
    }
    let stored = std::fs::read_to_string(VECTORS_PATH)
        .expect("vectors/vectors.txt is missing: create it with DIOPTRA_BLESS=1");
    let vectors = parse(&stored);
    let examples = examples();
    assert_eq!(vectors.len(), examples.len(), "one vector per example");
    for (vector, (request_id, message)) in vectors.iter().zip(examples) {
        assert_eq!(vector.name, variant_name(&message));
        assert_eq!(vector.request_id, request_id, "{}", vector.name);
        assert_eq!(
            hex::encode(wire(request_id, &message)),
            hex::encode(&vector.bytes),
            "{} encodes differently from the stored vector",
            vector.name
        );
        assert_eq!(
            decode_frame(&vector.bytes),
            Ok(Frame {
                version: PROTOCOL_VERSION,
                request_id,
                message
            }),
            "{} decodes differently",
            vector.name
        );
    }
}

#[test]
fn examples_cover_every_variant_once() {
    // The first payload byte is the discriminant (one varint byte while there are < 128).
    let mut discriminants: Vec<u32> = examples()
        .iter()
        .map(|(_, message)| {
            let mut buf = [0u8; 128];
            let payload = postcard::to_slice(message, &mut buf).expect("fits");
            u32::from(payload[0])
        })
        .collect();
    discriminants.sort_unstable();
    assert_eq!(
        discriminants,
        (0..MESSAGE_VARIANT_COUNT).collect::<Vec<_>>()
    );
    // And there is no variant past the count: serde itself refuses that index.
    let past_the_end = [u8::try_from(MESSAGE_VARIANT_COUNT).expect("< 128 variants")];
    assert_eq!(
        postcard::from_bytes::<Message>(&past_the_end),
        Err(postcard::Error::SerdeDeCustom)
    );
}
