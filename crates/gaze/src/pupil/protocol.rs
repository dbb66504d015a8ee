//! Pupil Capture's message layouts, decoded into typed values: Pupil Remote's string replies
//! and the msgpack gaze datums of the IPC backbone. No I/O here; every decoder takes any bytes
//! and returns an error or a value, never panics.
//!
//! A 3D gaze datum is a msgpack map. Binocular (`gaze.3d.01.`): `eye_centers_3d` and
//! `gaze_normals_3d`, maps keyed by eye id ("0"/"1" in current Capture, integers in older
//! versions); monocular (`gaze.3d.0.` / `gaze.3d.1.`): `eye_center_3d` and `gaze_normal_3d`.
//! Both: `gaze_point_3d`, `norm_pos`, `confidence`, `timestamp` (Pupil time, s) and
//! `base_data`, the pupil datums it was mapped from (`id`, `diameter_3d` in mm, ...).
//! Coordinates are the world camera's: x right, y down, z forward, millimetres.

use dioptra_core::EyeRay;
use rmpv::Value;

use super::ids::{
    BINOCULAR_TOPIC, GAZE_3D_TOPIC, LEFT_EYE_ID, MONOCULAR_LEFT_TOPIC, MONOCULAR_RIGHT_TOPIC,
    RIGHT_EYE_ID,
};

/// Why a reply or a datum could not be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct DecodeError(pub String);

fn err(m: impl Into<String>) -> DecodeError {
    DecodeError(m.into())
}

/// The reply to `SUB_PORT` / `PUB_PORT`: a TCP port number.
pub fn parse_port(reply: &str) -> Result<u16, DecodeError> {
    match reply.trim().parse::<u16>() {
        Ok(p) if p > 0 => Ok(p),
        _ => Err(err(format!("expected a port number, got {reply:?}"))),
    }
}

/// The reply to `t`: Pupil time in seconds (Python's repr of a float).
pub fn parse_time(reply: &str) -> Result<f64, DecodeError> {
    match reply.trim().parse::<f64>() {
        Ok(t) if t.is_finite() => Ok(t),
        _ => Err(err(format!("expected a time in seconds, got {reply:?}"))),
    }
}

/// Which gaze topic a datum came on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GazeTopic {
    Binocular,
    /// One eye, by Pupil's eye id (0 right, 1 left).
    Monocular(u8),
}

impl GazeTopic {
    /// The kind of a `gaze.3d.*` topic; `None` for any other topic.
    pub fn of(topic: &str) -> Option<GazeTopic> {
        // Capture may append a suffix after the eye ids (e.g. a mapper name): match prefixes.
        if topic.starts_with(BINOCULAR_TOPIC) {
            Some(GazeTopic::Binocular)
        } else if topic.starts_with(MONOCULAR_RIGHT_TOPIC) {
            Some(GazeTopic::Monocular(RIGHT_EYE_ID))
        } else if topic.starts_with(MONOCULAR_LEFT_TOPIC) {
            Some(GazeTopic::Monocular(LEFT_EYE_ID))
        } else {
            None
        }
    }
}

/// One eye's 3D gaze as Pupil reports it, in its world-camera frame (x right, y down,
/// z forward, mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PupilEye {
    /// Centre of the eyeball, mm.
    pub center_mm: [f64; 3],
    /// Gaze direction (Pupil sends unit vectors; not relied upon).
    pub normal: [f64; 3],
    /// Pupil diameter from the eye's pupil datum in `base_data`, mm.
    pub diameter_3d_mm: Option<f64>,
}

/// A decoded 3D gaze datum. Fields that are missing, of the wrong type or not finite are
/// `None`; only a usable `timestamp` is required.
#[derive(Debug, Clone, PartialEq)]
pub struct GazeDatum {
    pub topic: GazeTopic,
    /// Pupil time, seconds.
    pub timestamp_s: f64,
    pub confidence: Option<f64>,
    pub right: Option<PupilEye>,
    pub left: Option<PupilEye>,
    pub gaze_point_3d_mm: Option<[f64; 3]>,
    pub norm_pos: Option<[f64; 2]>,
}

/// Decodes the payload frame of a message on `topic`. Errors: the topic is not a 3D gaze
/// topic, the payload is not one msgpack map, or it has no finite `timestamp`.
pub fn decode_gaze(topic: &str, payload: &[u8]) -> Result<GazeDatum, DecodeError> {
    let kind = GazeTopic::of(topic)
        .ok_or_else(|| err(format!("{topic:?} is not a {GAZE_3D_TOPIC}* topic")))?;
    let mut rd = payload;
    let value = rmpv::decode::read_value(&mut rd)
        .map_err(|e| err(format!("the payload is not msgpack: {e}")))?;
    if !rd.is_empty() {
        return Err(err(format!(
            "{} bytes after the payload's msgpack value",
            rd.len()
        )));
    }
    let Value::Map(map) = &value else {
        return Err(err("the payload is not a msgpack map"));
    };
    let timestamp_s =
        number(get(map, "timestamp")).ok_or_else(|| err("the datum has no numeric timestamp"))?;
    let diameters = pupil_diameters(get(map, "base_data"));
    let eye = |center: Option<&Value>, normal: Option<&Value>, id: u8| {
        Some(PupilEye {
            center_mm: vec3(center?)?,
            normal: vec3(normal?)?,
            diameter_3d_mm: diameters[usize::from(id)],
        })
    };
    let (right, left) = match kind {
        GazeTopic::Binocular => {
            let (centers, normals) = (get(map, "eye_centers_3d"), get(map, "gaze_normals_3d"));
            let per_eye = |id: u8| {
                eye(
                    centers.and_then(|c| by_eye_id(c, id)),
                    normals.and_then(|n| by_eye_id(n, id)),
                    id,
                )
            };
            (per_eye(RIGHT_EYE_ID), per_eye(LEFT_EYE_ID))
        }
        GazeTopic::Monocular(id) => {
            let e = eye(get(map, "eye_center_3d"), get(map, "gaze_normal_3d"), id);
            if id == RIGHT_EYE_ID {
                (e, None)
            } else {
                (None, e)
            }
        }
    };
    Ok(GazeDatum {
        topic: kind,
        timestamp_s,
        confidence: number(get(map, "confidence")),
        right,
        left,
        gaze_point_3d_mm: get(map, "gaze_point_3d").and_then(vec3),
        norm_pos: get(map, "norm_pos").and_then(|v| {
            let a = numbers(v)?;
            (a.len() == 2).then(|| [a[0], a[1]])
        }),
    })
}

/// The value under string key `key` of a msgpack map.
fn get<'a>(map: &'a [(Value, Value)], key: &str) -> Option<&'a Value> {
    map.iter()
        .find(|(k, _)| k.as_str() == Some(key))
        .map(|(_, v)| v)
}

/// The entry for eye `id` of a per-eye map: keyed "0"/"1" (current Capture) or 0/1 (older).
fn by_eye_id(v: &Value, id: u8) -> Option<&Value> {
    let Value::Map(m) = v else { return None };
    let text = if id == 0 { "0" } else { "1" };
    m.iter()
        .find(|(k, _)| k.as_str() == Some(text) || k.as_u64() == Some(u64::from(id)))
        .map(|(_, v)| v)
}

/// A finite number, integer or float.
fn number(v: Option<&Value>) -> Option<f64> {
    let x = match v? {
        Value::F64(x) => *x,
        Value::F32(x) => f64::from(*x),
        Value::Integer(i) => i.as_f64()?,
        _ => return None,
    };
    x.is_finite().then_some(x)
}

fn numbers(v: &Value) -> Option<Vec<f64>> {
    let Value::Array(a) = v else { return None };
    if a.len() > 3 {
        return None;
    }
    a.iter().map(|x| number(Some(x))).collect()
}

fn vec3(v: &Value) -> Option<[f64; 3]> {
    let a = numbers(v)?;
    (a.len() == 3).then(|| [a[0], a[1], a[2]])
}

/// `diameter_3d` of eye 0's and eye 1's pupil datum in `base_data`.
fn pupil_diameters(base: Option<&Value>) -> [Option<f64>; 2] {
    let mut out = [None, None];
    let Some(Value::Array(items)) = base else {
        return out;
    };
    for item in items {
        let Value::Map(m) = item else { continue };
        let id = get(m, "id").and_then(Value::as_u64);
        if let Some(id @ 0..=1) = id {
            out[id as usize] = number(get(m, "diameter_3d")).filter(|d| *d > 0.0);
        }
    }
    out
}

/// Pupil's world-camera frame (y down) to dioptra's head frame (y up); x and z agree, both mm.
pub fn to_dioptra_frame(v: [f64; 3]) -> [f32; 3] {
    [v[0] as f32, -v[1] as f32, v[2] as f32]
}

/// One eye as core's [`EyeRay`]: valid when Pupil sent the eye and `trusted` (the datum's
/// confidence reached the threshold), and the ray is finite with a direction.
pub fn eye_ray(eye: Option<&PupilEye>, trusted: bool) -> EyeRay {
    let Some(e) = eye else {
        return invalid_eye();
    };
    let origin = to_dioptra_frame(e.center_mm);
    let d = to_dioptra_frame(e.normal);
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let finite = origin.iter().chain(&d).all(|v| v.is_finite());
    if !(trusted && finite && n > 1e-6) {
        return EyeRay {
            origin_mm: if finite { origin } else { [0.0; 3] },
            ..invalid_eye()
        };
    }
    EyeRay {
        origin_mm: origin,
        direction: [d[0] / n, d[1] / n, d[2] / n],
        pupil_mm: e.diameter_3d_mm.map_or(f32::NAN, |d| d as f32),
        valid: true,
    }
}

/// An eye the tracker did not see (the HID drivers' dropout: `valid: false`).
fn invalid_eye() -> EyeRay {
    EyeRay {
        origin_mm: [0.0; 3],
        direction: [0.0, 0.0, 1.0],
        pupil_mm: f32::NAN,
        valid: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_parse_or_name_what_came() {
        assert_eq!(parse_port("50021"), Ok(50021));
        assert!(parse_port("0").is_err());
        assert!(parse_port("Unknown command.")
            .unwrap_err()
            .0
            .contains("Unknown"));
        assert_eq!(parse_time("1234.5"), Ok(1234.5));
        assert!(parse_time("nan").is_err());
        assert!(parse_time("inf").is_err());
    }

    #[test]
    fn topics_are_matched_by_prefix() {
        assert_eq!(GazeTopic::of("gaze.3d.01."), Some(GazeTopic::Binocular));
        assert_eq!(GazeTopic::of("gaze.3d.0."), Some(GazeTopic::Monocular(0)));
        assert_eq!(
            GazeTopic::of("gaze.3d.1._mapper"),
            Some(GazeTopic::Monocular(1))
        );
        assert_eq!(GazeTopic::of("gaze.2d.01."), None);
        assert_eq!(GazeTopic::of("pupil.0.3d"), None);
    }

    #[test]
    fn y_down_becomes_y_up() {
        assert_eq!(to_dioptra_frame([1.0, 2.0, 3.0]), [1.0, -2.0, 3.0]);
        let e = PupilEye {
            center_mm: [30.0, 10.0, -20.0],
            normal: [0.0, 0.6, 0.8],
            diameter_3d_mm: Some(3.5),
        };
        let r = eye_ray(Some(&e), true);
        assert!(r.valid);
        assert_eq!(r.origin_mm, [30.0, -10.0, -20.0]);
        assert!((r.direction[1] + 0.6).abs() < 1e-6, "{r:?}");
        assert_eq!(r.pupil_mm, 3.5);
        assert!(!eye_ray(Some(&e), false).valid);
        assert!(!eye_ray(None, true).valid);
        let zero = PupilEye {
            normal: [0.0; 3],
            ..e
        };
        assert!(!eye_ray(Some(&zero), true).valid);
    }
}
