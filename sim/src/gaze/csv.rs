//! Recorded gaze traces as CSV, for replay through the simulated trackers.
//!
//! Header (required, this order): `device_time_us`, then for `left_` and `right_`:
//! `valid,ox,oy,oz,dx,dy,dz,pupil_mm` (origin mm, unit direction, head frame). `#` lines
//! are comments.

use dioptra_protocol::{BinocularSample, EyeSample};

use super::generator::SampleSource;

const EYE_COLS: [&str; 8] = ["valid", "ox", "oy", "oz", "dx", "dy", "dz", "pupil_mm"];

/// The header line.
pub fn header() -> String {
    let mut cols = vec!["device_time_us".to_string()];
    for side in ["left", "right"] {
        cols.extend(EYE_COLS.iter().map(|c| format!("{side}_{c}")));
    }
    cols.join(",")
}

/// A CSV line that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("gaze CSV line {line}: {detail}")]
pub struct CsvError {
    pub line: usize,
    pub detail: String,
}

/// Parses a trace. Device times must increase.
pub fn parse(text: &str) -> Result<Vec<BinocularSample>, CsvError> {
    let mut out = Vec::new();
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let err = |line, detail: String| CsvError { line, detail };
    match lines.next() {
        Some((_, h)) if h.replace(' ', "") == header() => {}
        Some((n, _)) => return Err(err(n, format!("expected the header `{}`", header()))),
        None => return Err(err(0, "empty trace".into())),
    }
    for (n, l) in lines {
        let cols: Vec<&str> = l.split(',').map(str::trim).collect();
        if cols.len() != 17 {
            return Err(err(n, format!("{} columns, expected 17", cols.len())));
        }
        let time: u64 = cols[0]
            .parse()
            .map_err(|_| err(n, format!("bad device_time_us `{}`", cols[0])))?;
        let eye = |c: &[&str]| -> Result<EyeSample, CsvError> {
            let valid = match c[0] {
                "1" | "true" => true,
                "0" | "false" => false,
                v => return Err(err(n, format!("bad valid flag `{v}`"))),
            };
            let mut f = [0f32; 7];
            for (i, s) in c[1..].iter().enumerate() {
                f[i] = s.parse().map_err(|_| err(n, format!("bad number `{s}`")))?;
            }
            Ok(EyeSample {
                origin_mm: [f[0], f[1], f[2]],
                direction: [f[3], f[4], f[5]],
                pupil_mm: f[6],
                valid,
            })
        };
        let s = BinocularSample {
            device_time_us: time,
            left: eye(&cols[1..9])?,
            right: eye(&cols[9..17])?,
        };
        if out
            .last()
            .is_some_and(|p: &BinocularSample| p.device_time_us >= time)
        {
            return Err(err(n, "device time does not increase".into()));
        }
        out.push(s);
    }
    Ok(out)
}

/// Writes a trace that [`parse`] reads back.
pub fn write(samples: &[BinocularSample]) -> String {
    let mut s = header();
    s.push('\n');
    for b in samples {
        s.push_str(&b.device_time_us.to_string());
        for e in [&b.left, &b.right] {
            let o = e.origin_mm;
            let d = e.direction;
            s.push_str(&format!(
                ",{},{},{},{},{},{},{},{}",
                u8::from(e.valid),
                o[0],
                o[1],
                o[2],
                d[0],
                d[1],
                d[2],
                e.pupil_mm
            ));
        }
        s.push('\n');
    }
    s
}

/// Replays a trace at its recorded timing, once.
#[derive(Debug, Clone)]
pub struct Replay {
    samples: Vec<BinocularSample>,
    next: usize,
    rate_hz: f64,
}

impl Replay {
    pub fn new(samples: Vec<BinocularSample>) -> Self {
        let rate_hz = match (samples.first(), samples.last()) {
            (Some(a), Some(b)) if samples.len() > 1 && b.device_time_us > a.device_time_us => {
                (samples.len() - 1) as f64 * 1e6 / (b.device_time_us - a.device_time_us) as f64
            }
            _ => 0.0,
        };
        Replay {
            samples,
            next: 0,
            rate_hz,
        }
    }
}

impl SampleSource for Replay {
    fn next_sample(&mut self) -> Option<(u64, BinocularSample)> {
        let first = self.samples.first()?.device_time_us;
        let s = *self.samples.get(self.next)?;
        self.next += 1;
        Some((s.device_time_us - first, s))
    }
    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }
}

#[cfg(test)]
mod tests {
    use super::super::generator::{GazeGenerator, GeneratorConfig, Scene};
    use super::*;

    #[test]
    fn round_trips_and_replays_with_timing() {
        let mut g = GazeGenerator::new(
            Scene::named("saccades").unwrap(),
            GeneratorConfig::default(),
        )
        .unwrap();
        let samples: Vec<BinocularSample> = (0..50).map(|_| g.next_truth().reported).collect();
        let text = write(&samples);
        assert_eq!(parse(&text).unwrap(), samples);
        let mut r = Replay::new(parse(&format!("# recorded\n{text}")).unwrap());
        assert!((r.rate_hz() - 500.0).abs() < 0.1);
        let (t0, _) = r.next_sample().unwrap();
        let (t1, s1) = r.next_sample().unwrap();
        assert_eq!((t0, s1), (0, samples[1]));
        assert!((1999..=2001).contains(&t1));
    }

    #[test]
    fn bad_lines_name_the_line() {
        let h = header();
        assert_eq!(parse("").unwrap_err().line, 0);
        assert_eq!(parse("a,b\n").unwrap_err().line, 1);
        let row = "5,1,0,0,0,0,0,1,4,1,0,0,0,0,0,1,4";
        assert!(parse(&format!("{h}\n{row}\n")).is_ok());
        let e = parse(&format!("{h}\n{row}\n{row}\n")).unwrap_err();
        assert_eq!(e.line, 3);
        assert!(e.to_string().contains("increase"));
        assert_eq!(parse(&format!("{h}\n5,2,0\n")).unwrap_err().line, 2);
        let e = parse(&format!("{h}\n5,2,0,0,0,0,0,1,4,1,0,0,0,0,0,1,4\n")).unwrap_err();
        assert!(e.detail.contains("valid"));
        let e = parse(&format!("{h}\n5,1,x,0,0,0,0,1,4,1,0,0,0,0,0,1,4\n")).unwrap_err();
        assert!(e.detail.contains("`x`"));
    }
}
