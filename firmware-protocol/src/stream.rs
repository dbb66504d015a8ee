//! Stream decoder: turns bytes arriving in arbitrary chunks into frames, in fixed memory.

use core::iter::FusedIterator;

use cobs::{DecodeResult, DecoderState};

use crate::frame::{decode_body, DecodeError, Frame, MAX_BODY_LEN};

/// Accumulates a byte stream and yields one result per delimited frame, in order.
///
/// COBS is decoded as bytes arrive, so the decoder holds one body ([`MAX_BODY_LEN`] bytes) and
/// nothing else. After any error it resynchronises at the next 0x00. Empty frames (a 0x00
/// right after another, as senders may use to flush line noise) are skipped silently.
#[derive(Debug)]
pub struct FrameDecoder {
    body: [u8; MAX_BODY_LEN],
    body_len: usize,
    cobs: DecoderState,
    /// Set after an oversized run was reported: ignore bytes until the next delimiter.
    discarding: bool,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            body: [0; MAX_BODY_LEN],
            body_len: 0,
            cobs: DecoderState::Idle,
            discarding: false,
        }
    }

    /// Drops any partly received frame (e.g. after reopening the link).
    pub fn reset(&mut self) {
        self.body_len = 0;
        self.cobs = DecoderState::Idle;
        self.discarding = false;
    }

    /// Feeds `bytes`; the returned iterator yields each frame they complete, in order.
    ///
    /// Bytes are consumed as the iterator advances. Dropping it early still feeds the rest
    /// (so the stream stays in step) but discards the frames they complete.
    #[must_use = "frames are yielded by the returned iterator"]
    pub fn push<'d, 'b>(&'d mut self, bytes: &'b [u8]) -> Frames<'d, 'b> {
        Frames {
            decoder: self,
            bytes,
        }
    }

    /// Feeds one byte; returns a result when it ends a frame (or an oversized run). Suits an
    /// interrupt handler that sees one byte at a time.
    pub fn push_byte(&mut self, byte: u8) -> Option<Result<Frame, DecodeError>> {
        if self.discarding {
            self.discarding = byte != 0;
            return None;
        }
        match self.cobs.feed(byte) {
            Ok(DecodeResult::NoData) => None,
            Ok(DecodeResult::DataContinue(decoded)) => {
                if let Some(slot) = self.body.get_mut(self.body_len) {
                    *slot = decoded;
                    self.body_len += 1;
                    None
                } else {
                    // COBS emits data only for non-zero input, so this byte is not a delimiter.
                    self.reset();
                    self.discarding = true;
                    Some(Err(DecodeError::TooLong))
                }
            }
            Ok(DecodeResult::DataComplete) => {
                let body = self.body.get(..self.body_len).unwrap_or_default();
                let result = decode_body(body);
                self.body_len = 0;
                Some(result)
            }
            // COBS errors happen only at a 0x00, after which the COBS state is idle again.
            Err(_) => {
                self.body_len = 0;
                Some(Err(DecodeError::Cobs))
            }
        }
    }
}

/// Iterator over the frames completed by one [`FrameDecoder::push`].
#[derive(Debug)]
pub struct Frames<'d, 'b> {
    decoder: &'d mut FrameDecoder,
    bytes: &'b [u8],
}

impl Iterator for Frames<'_, '_> {
    type Item = Result<Frame, DecodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        while let Some((&byte, rest)) = self.bytes.split_first() {
            self.bytes = rest;
            if let Some(result) = self.decoder.push_byte(byte) {
                return Some(result);
            }
        }
        None
    }
}

impl FusedIterator for Frames<'_, '_> {}

impl Drop for Frames<'_, '_> {
    fn drop(&mut self) {
        for &byte in self.bytes {
            // The caller stopped iterating: keep the stream state, drop the results.
            let _ = self.decoder.push_byte(byte);
        }
    }
}
