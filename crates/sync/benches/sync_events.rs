//! Host-side cost per sync event. Target: <= 5 us median each.
//! - sync board: stream-decode one `SubframeEvent` frame and map its device time to host time
//!   through a drift-fitted clock mapping;
//! - DLPC350: reassemble a status reply report and decode it.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{ClockMapper, Timestamp};
use dioptra_protocol::{encode_frame, FrameDecoder, Message, SubframeEvent, MAX_FRAME_LEN};
use dioptra_sync::board::to_sequencer_event;
use dioptra_sync::dlpc350::protocol::{
    Assembler, Command, Direction, GetMainStatus, MainStatus, Packet,
};

fn board_event(c: &mut Criterion) {
    let mut wire = [0u8; MAX_FRAME_LEN];
    let event = Message::SubframeEvent(SubframeEvent {
        frame: 1234,
        plane_index: 3,
        device_time_us: 9_876_543_210,
        lens_power_d: 1.401,
    });
    let len = encode_frame(0, &event, &mut wire).expect("fits");
    // 16 exchanges over 4 s on a clock 7 s ahead and 30 ppm fast: drift is fitted.
    let mut mapper = ClockMapper::new();
    for i in 0..16u64 {
        let host = Timestamp::from_millis(250 * i);
        let device = 7_000_000 + (host.as_micros() as f64 * 1.000_03) as u64;
        mapper.add_exchange(
            host,
            device + 40,
            host + std::time::Duration::from_micros(80),
        );
    }
    let mut decoder = FrameDecoder::new();
    c.bench_function("sync_board/decode_and_map_subframe_event", |b| {
        b.iter(|| {
            let mut out = None;
            for frame in decoder.push(black_box(&wire[..len])).flatten() {
                out = to_sequencer_event(&frame.message, Timestamp(5), &mapper);
            }
            out.expect("one event")
        })
    });
}

fn dlpc350_reply(c: &mut Criterion) {
    let request = Packet::request(true, 9, GetMainStatus::CODE, vec![]);
    let reply = Packet::reply_to(&request, false, GetMainStatus::encode_reply(&MainStatus(2)));
    let report = reply.to_reports().expect("fits")[0];
    c.bench_function("dlpc350/reassemble_and_decode_status_reply", |b| {
        b.iter(|| {
            let mut asm = Assembler::new(Direction::Reply);
            let p = asm
                .push(black_box(&report))
                .expect("valid")
                .expect("complete");
            GetMainStatus::decode_reply(&p.data).expect("decodes")
        })
    });
}

criterion_group!(benches, board_event, dlpc350_reply);
criterion_main!(benches);
