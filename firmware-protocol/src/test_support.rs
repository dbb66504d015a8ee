//! Example messages and proptest strategies shared by the tests.

use std::vec;
use std::vec::Vec;

use heapless::String;
use proptest::prelude::*;

use crate::message::*;
use crate::PROTOCOL_VERSION;

/// One example of every message variant with the request id it would travel under: the golden
/// vectors. Values are distinctive (multi-byte varints, negative and fractional floats) so a
/// layout mistake shows.
pub(crate) fn examples() -> Vec<(u16, Message)> {
    let left = EyeSample {
        origin_mm: [-31.5, 0.25, 12.0],
        direction: [0.0, 0.0, 1.0],
        pupil_mm: 4.0,
        valid: true,
    };
    let right = EyeSample {
        origin_mm: [31.5, 0.25, 12.0],
        direction: [0.6, 0.0, 0.8],
        pupil_mm: 0.0,
        valid: false,
    };
    std::vec![
        (
            1,
            Message::Hello {
                protocol_version: PROTOCOL_VERSION.into(),
            },
        ),
        (
            1,
            Message::DeviceInfo(DeviceInfo {
                kind: DeviceKind::SyncBoard,
                protocol_version: PROTOCOL_VERSION.into(),
                firmware_version: FirmwareVersion {
                    major: 1,
                    minor: 2,
                    patch: 300,
                },
                serial: truncated("DSB-0042"),
                capabilities: Capabilities::PLANE_SCHEDULE.with(Capabilities::TIME_SYNC),
            }),
        ),
        (1, Message::Ack),
        (
            513,
            Message::error(ErrorCode::OutOfRange, "power 9.0 D > max 5.0 D"),
        ),
        (
            2,
            Message::TimeSyncPing {
                host_time_us: 1_700_000_000_000_000,
            },
        ),
        (
            2,
            Message::TimeSyncPong {
                host_time_us: 1_700_000_000_000_000,
                device_time_us: 123_456_789,
            },
        ),
        (
            3,
            Message::SetFocalPower {
                diopters: -1.25,
                apply_at_us: 123_460_000,
            },
        ),
        (4, Message::GetLensState),
        (
            4,
            Message::LensState(LensState {
                power_d: 1.5,
                current_ma: 87.25,
                temperature_c: 31.0625,
                settled: true,
                device_time_us: 123_470_000,
            }),
        ),
        (5, Message::GetLimits),
        (
            5,
            Message::Limits(Limits {
                min_power_d: -2.0,
                max_power_d: 3.0,
                max_current_ma: 292.84,
            }),
        ),
        (
            6,
            Message::PlaneSchedule(
                PlaneSchedule::new(&[0.2, 0.8, 1.4, 2.0], 4_166, 1_500, true)
                    .expect("the example schedule is valid"),
            ),
        ),
        (7, Message::Start),
        (65_535, Message::Stop),
        (
            0,
            Message::SubframeEvent(SubframeEvent {
                frame: 1_000,
                plane_index: 3,
                device_time_us: 124_000_000,
                lens_power_d: 1.98,
            }),
        ),
        (
            0,
            Message::Fault(Fault {
                kind: FaultKind::LateSettle,
                frame: 1_001,
                plane_index: 2,
                device_time_us: 124_004_000,
            }),
        ),
        (
            0,
            Message::BinocularSample(BinocularSample {
                device_time_us: 124_008_333,
                left,
                right,
            }),
        ),
        (
            8,
            Message::PhotodiodeConfig(PhotodiodeConfig {
                enabled: true,
                threshold: 32_768,
                hysteresis: 2_000,
            }),
        ),
        (
            0,
            Message::PhotodiodeEdge(PhotodiodeEdge {
                edge: 300,
                device_time_us: 124_011_111,
                rising: true,
                level: 51_234,
            }),
        ),
    ]
}

/// The largest instance of each variant whose size varies, to prove they fit a frame.
pub(crate) fn largest_messages() -> Vec<Message> {
    let eye = EyeSample {
        origin_mm: [f32::MAX; 3],
        direction: [f32::MIN; 3],
        pupil_mm: f32::MAX,
        valid: true,
    };
    std::vec![
        Message::DeviceInfo(DeviceInfo {
            kind: DeviceKind::EyeTracker,
            protocol_version: u16::MAX,
            firmware_version: FirmwareVersion {
                major: u16::MAX,
                minor: u16::MAX,
                patch: u16::MAX,
            },
            serial: truncated("ZZZZZZZZZZZZZZZZZZZZ"),
            capabilities: Capabilities(u32::MAX),
        }),
        Message::error(ErrorCode::Internal, &"é".repeat(ERROR_DETAIL_LEN)),
        Message::TimeSyncPong {
            host_time_us: u64::MAX,
            device_time_us: u64::MAX,
        },
        Message::PlaneSchedule(PlaneSchedule {
            plane_powers_d: heapless::Vec::from_slice(&[1.0; MAX_PLANES]).unwrap_or_default(),
            subframe_period_us: u32::MAX,
            settle_allowance_us: u32::MAX,
            trigger_rising: true,
        }),
        Message::SubframeEvent(SubframeEvent {
            frame: u32::MAX,
            plane_index: u8::MAX,
            device_time_us: u64::MAX,
            lens_power_d: 1.0,
        }),
        Message::Fault(Fault {
            kind: FaultKind::LateApply,
            frame: u32::MAX,
            plane_index: u8::MAX,
            device_time_us: u64::MAX,
        }),
        Message::BinocularSample(BinocularSample {
            device_time_us: u64::MAX,
            left: eye,
            right: eye,
        }),
        Message::PhotodiodeConfig(PhotodiodeConfig {
            enabled: true,
            threshold: u16::MAX,
            hysteresis: u16::MAX,
        }),
        Message::PhotodiodeEdge(PhotodiodeEdge {
            edge: u32::MAX,
            device_time_us: u64::MAX,
            rising: true,
            level: u16::MAX,
        }),
    ]
}

/// Any f32 except NaN, so that decoded messages compare equal with `==` (NaN payloads are
/// checked bit-exactly in their own test).
fn float() -> impl Strategy<Value = f32> {
    use proptest::num::f32::{INFINITE, NEGATIVE, NORMAL, POSITIVE, SUBNORMAL, ZERO};
    POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO | INFINITE
}

fn text<const N: usize>() -> impl Strategy<Value = String<N>> {
    any::<std::string::String>().prop_map(|s| truncated::<N>(&s))
}

fn eye() -> impl Strategy<Value = EyeSample> {
    (
        [float(), float(), float()],
        [float(), float(), float()],
        float(),
        any::<bool>(),
    )
        .prop_map(|(origin_mm, direction, pupil_mm, valid)| EyeSample {
            origin_mm,
            direction,
            pupil_mm,
            valid,
        })
}

/// Any message, including ones a device would refuse (the wire carries them all).
pub(crate) fn any_message() -> impl Strategy<Value = Message> {
    let device_kind = prop_oneof![
        Just(DeviceKind::Lens),
        Just(DeviceKind::SyncBoard),
        Just(DeviceKind::EyeTracker)
    ];
    let fault_kind = prop_oneof![
        Just(FaultKind::MissedVsync),
        Just(FaultKind::LateSettle),
        Just(FaultKind::Overtemperature),
        Just(FaultKind::Overcurrent),
        Just(FaultKind::LateApply),
    ];
    prop_oneof![
        any::<u16>().prop_map(|protocol_version| Message::Hello { protocol_version }),
        (
            device_kind,
            any::<u16>(),
            any::<[u16; 3]>(),
            text::<SERIAL_LEN>(),
            any::<u32>()
        )
            .prop_map(
                |(kind, protocol_version, [major, minor, patch], serial, caps)| {
                    Message::DeviceInfo(DeviceInfo {
                        kind,
                        protocol_version,
                        firmware_version: FirmwareVersion {
                            major,
                            minor,
                            patch,
                        },
                        serial,
                        capabilities: Capabilities(caps),
                    })
                }
            ),
        Just(Message::Ack),
        (
            prop::sample::select(&ErrorCode::ALL[..]),
            text::<ERROR_DETAIL_LEN>()
        )
            .prop_map(|(code, detail)| Message::Error { code, detail }),
        any::<u64>().prop_map(|host_time_us| Message::TimeSyncPing { host_time_us }),
        (any::<u64>(), any::<u64>()).prop_map(|(host_time_us, device_time_us)| {
            Message::TimeSyncPong {
                host_time_us,
                device_time_us,
            }
        }),
        (float(), any::<u64>()).prop_map(|(diopters, apply_at_us)| Message::SetFocalPower {
            diopters,
            apply_at_us
        }),
        Just(Message::GetLensState),
        (float(), float(), float(), any::<bool>(), any::<u64>()).prop_map(
            |(power_d, current_ma, temperature_c, settled, device_time_us)| {
                Message::LensState(LensState {
                    power_d,
                    current_ma,
                    temperature_c,
                    settled,
                    device_time_us,
                })
            }
        ),
        Just(Message::GetLimits),
        (float(), float(), float()).prop_map(|(min_power_d, max_power_d, max_current_ma)| {
            Message::Limits(Limits {
                min_power_d,
                max_power_d,
                max_current_ma,
            })
        }),
        (
            prop::collection::vec(float(), 0..=MAX_PLANES),
            any::<u32>(),
            any::<u32>(),
            any::<bool>()
        )
            .prop_map(
                |(powers, subframe_period_us, settle_allowance_us, trigger_rising)| {
                    Message::PlaneSchedule(PlaneSchedule {
                        plane_powers_d: heapless::Vec::from_slice(&powers).unwrap_or_default(),
                        subframe_period_us,
                        settle_allowance_us,
                        trigger_rising,
                    })
                }
            ),
        Just(Message::Start),
        Just(Message::Stop),
        (any::<u32>(), any::<u8>(), any::<u64>(), float()).prop_map(
            |(frame, plane_index, device_time_us, lens_power_d)| {
                Message::SubframeEvent(SubframeEvent {
                    frame,
                    plane_index,
                    device_time_us,
                    lens_power_d,
                })
            }
        ),
        (fault_kind, any::<u32>(), any::<u8>(), any::<u64>()).prop_map(
            |(kind, frame, plane_index, device_time_us)| {
                Message::Fault(Fault {
                    kind,
                    frame,
                    plane_index,
                    device_time_us,
                })
            }
        ),
        (any::<u64>(), eye(), eye()).prop_map(|(device_time_us, left, right)| {
            Message::BinocularSample(BinocularSample {
                device_time_us,
                left,
                right,
            })
        }),
        (any::<bool>(), any::<u16>(), any::<u16>()).prop_map(|(enabled, threshold, hysteresis)| {
            Message::PhotodiodeConfig(PhotodiodeConfig {
                enabled,
                threshold,
                hysteresis,
            })
        }),
        (any::<u32>(), any::<u64>(), any::<bool>(), any::<u16>()).prop_map(
            |(edge, device_time_us, rising, level)| {
                Message::PhotodiodeEdge(PhotodiodeEdge {
                    edge,
                    device_time_us,
                    rising,
                    level,
                })
            }
        ),
    ]
}
