//! The demo's run: the rig, the summary and the scoring against ground truth.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use dioptra_core::{Diopters, RgbImage, Side, Timestamp};
use dioptra_render::metrics;
use dioptra_rig::config::{RigConfig, EXAMPLE_SIM_BINOCULAR_RIG, EXAMPLE_SIM_RIG};
use dioptra_rig::render::rgbd::RgbdRenderer;
use dioptra_rig::simulated_rig::{percentile, Run, SimRun};
use dioptra_sched::{Mode, Stage};
use hdrhistogram::Histogram;

use super::frames::{self, DemoFrames, Kept};
use super::render::Observed;
use super::{plots, Args};

pub(super) fn run_demo(args: Args) -> Result<()> {
    let mode: Mode = args.mode.parse().map_err(anyhow::Error::msg)?;
    if !(args.seconds > 0.0 && args.seconds <= 600.0) {
        bail!(
            "--seconds {} is out of range: expected more than 0 and at most 600",
            args.seconds
        );
    }
    if !(32..=1024).contains(&args.size) {
        bail!(
            "--size {} is out of range: expected 32 to 1024 pixels",
            args.size
        );
    }
    let auto = match args.method.as_str() {
        "gather" => false,
        "auto" if mode == Mode::Varifocal => true,
        "auto" => bail!(
            "--method auto plans varifocal frames only; {} mode renders with its own method (drop --method)",
            mode.as_str()
        ),
        other => bail!("--method {other:?} is unknown: expected gather or auto"),
    };
    let binocular = args.eyes == 2;
    if binocular && mode != Mode::Varifocal {
        bail!(
            "--eyes 2 runs the binocular example rig, which is varifocal (a lens per eye, no \
             sync board); drop --mode {} (the rig renders a layer set or a light-field panel \
             per eye on a stereo layout, but the demo shows varifocal only)",
            mode.as_str()
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    println!(
        "dioptra demo: {} mode, {} s of simulated time, {}x{} px{}, scene seed {}",
        mode.as_str(),
        args.seconds,
        args.size,
        args.size,
        if binocular {
            " per eye, two eyes side by side"
        } else {
            ""
        },
        args.seed
    );
    let cfg = demo_config(mode, args.size, auto, binocular)?;
    let mut sim =
        SimRun::new(cfg, Duration::from_secs_f64(args.seconds)).context("the demo's rig config")?;
    let frames = std::sync::Arc::new(
        DemoFrames::new(
            mode,
            args.seed,
            args.size,
            args.seconds,
            sim.sched.eye,
            sim.cfg
                .optics
                .planes
                .iter()
                .copied()
                .map(Diopters)
                .collect(),
        )?
        .with_eyes(binocular.then_some(sim.cfg.eye.ipd_mm * 0.5e-3)),
    );
    sim.spec.gaze_scene = frames.gaze_scene();
    // The rig's renderer, as `dioptra serve` makes it from the same config, watched.
    let renderer = std::sync::Arc::new(Observed::new(
        std::sync::Arc::new(
            RgbdRenderer::new(
                &sim.cfg.render,
                &sim.cfg.eye,
                &sim.cfg.display,
                &sim.cfg.optics,
            )
            .context("the demo's renderer")?,
        ),
        frames.keep_after(),
        frames.planes().to_vec(),
    ));
    println!("running the loop (simulated devices; progress every simulated second)...");
    let r: Run = sim
        .run_paused(Some(frames.clone()), renderer.clone(), None)
        .context("the simulated rig failed")?;
    println!(
        "\nran {:.1} s of simulated time in {:.1} s of wall time ({:.1}x real time)",
        r.simulated.as_secs_f64(),
        r.wall.as_secs_f64(),
        r.simulated.as_secs_f64() / r.wall.as_secs_f64().max(1e-9)
    );
    summary(&r, mode);
    if binocular {
        per_eye_summary(&r, &renderer);
    }
    if auto {
        let chosen: Vec<String> = renderer
            .planned()
            .iter()
            .map(|(m, n)| format!("{m} {n}"))
            .collect();
        println!(
            "method auto: the planner chose (frames) {} for a fovea PSNR target of {} dB",
            chosen.join(", "),
            dioptra_render::planner::Target::default().fovea_psnr_db
        );
    }
    let kept = renderer.take_kept();
    plots::latency(&args.out.join("latency.png"), &r)?;
    plots::focus(&args.out.join("focus.png"), &r, mode)?;
    if binocular {
        write_eyes(&frames, &kept, &args)?;
        println!(
            "\nwrote {}: frame_*_{{left,right}}_{{input,rendered}}.png, frame_*_stereo.png (side by side), latency.png, focus.png",
            args.out.display()
        );
        return Ok(());
    }
    score(&r, &frames, &kept, &args)?;
    println!(
        "\nwrote {}: frame_*_{{input,rendered,eye,truth}}.png, latency.png, focus.png",
        args.out.display()
    );
    Ok(())
}

/// Each eye's figures on the binocular rig: its lens's commands and focus error, its render.
fn per_eye_summary(r: &Run, renderer: &Observed) {
    println!("\n== per eye ==");
    for (lens, name) in [(0u8, "left"), (1, "right")] {
        let commands = r
            .log
            .lens_commands
            .iter()
            .filter(|c| c.lens.0 == lens)
            .count();
        // Fixating (not in a saccade or blink): the lens's power against the vergence depth.
        let errors: Vec<f64> = r
            .log
            .probes
            .iter()
            .filter(|p| p.phase == dioptra_sched::processing::EyePhase::Fixation)
            .filter_map(|p| {
                let power = if lens == 0 {
                    p.lens_power
                } else {
                    p.lens_power_right
                }?;
                Some((f64::from(power.0) - p.vergence_d?).abs())
            })
            .collect();
        let median = {
            let mut e = errors.clone();
            e.sort_by(f64::total_cmp);
            e.get(e.len() / 2).copied()
        };
        let render = renderer.eye_render_times(lens == 1);
        let (p50, p99) = (percentile(&render, 50.0), percentile(&render, 99.0));
        println!(
            "{name} eye: lens commands {commands}, median |lens power - vergence| while fixating {}, render {}",
            median.map_or("n/a".into(), |m| format!("{m:.3} D (n = {})", errors.len())),
            match (p50, p99) {
                (Some(a), Some(b)) => format!(
                    "p50 {:.2} ms, p99 {:.2} ms (n = {}, CPU, wall clock on this machine)",
                    a.as_secs_f64() * 1e3,
                    b.as_secs_f64() * 1e3,
                    render.len()
                ),
                _ => "none".into(),
            }
        );
    }
    // Both commands of one decision go out back to back: the same simulated instant.
    let mut pairs = 0;
    let mut same = 0;
    let cmds = &r.log.lens_commands;
    for w in cmds.windows(2) {
        if w[0].lens.0 == 0 && w[1].lens.0 == 1 {
            pairs += 1;
            same += usize::from(w[0].t == w[1].t);
        }
    }
    println!("lens command pairs {pairs}, both eyes' commands issued at the same instant: {same}");
    println!(
        "accuracy against thin-lens ground truth is scored for the one-eye demo only (the \
         reference renders the cyclopean eye); run without --eyes 2 for it"
    );
}

/// The kept frames' images per eye, and the side-by-side panel of each.
fn write_eyes(frames: &DemoFrames, kept: &[Kept], args: &Args) -> Result<()> {
    let mut index = 0;
    for pair in kept.chunks(2) {
        let [l, r] = pair else { continue };
        if (l.eye, r.eye) != (Some(Side::Left), Some(Side::Right)) || l.frame != r.frame {
            bail!("the kept frames are not one frame's two eyes");
        }
        let base = args.out.join(format!("frame_{index}"));
        index += 1;
        let mut rendered = Vec::new();
        for (k, name) in [(l, "left"), (r, "right")] {
            write(&base, &format!("{name}_input"), &k.input.color)?;
            for (what, img) in frames.rendered_images(k) {
                write(&base, &format!("{name}_{what}"), &img)?;
                if what == "rendered" {
                    rendered.push(img);
                }
            }
        }
        if let [a, b] = rendered.as_slice() {
            write(&base, "stereo", &side_by_side(a, b)?)?;
        }
    }
    Ok(())
}

/// `a` and `b` side by side, placed as the rig's side-by-side sinks place them (1:1, each
/// centred in its half).
fn side_by_side(a: &RgbImage, b: &RgbImage) -> Result<RgbImage> {
    use dioptra_rig::config::{DisplayLayout, EyeOffsets, Scale};
    use dioptra_rig::display::placement::{draw_into, PlacementConfig};
    let (w, h) = (a.width(), a.height());
    let config = PlacementConfig {
        layout: DisplayLayout::SideBySide,
        scale: Scale::Exact,
        offsets: EyeOffsets::default(),
    };
    let surface = (u32::try_from(2 * w)?, u32::try_from(h)?);
    let mut panel = RgbImage::new(2 * w, h, [0.0; 3]);
    for (side, img) in [(Side::Left, a), (Side::Right, b)] {
        let size = (u32::try_from(img.width())?, u32::try_from(img.height())?);
        let rect = config
            .placement(surface, Some(side), size)
            .map_err(|m| anyhow::anyhow!("{m}"))?;
        draw_into(&mut panel, img, rect);
    }
    Ok(panel)
}

fn ms(us: u64) -> f64 {
    us as f64 / 1000.0
}

fn p50_p99(h: &Histogram<u64>) -> String {
    if h.is_empty() {
        return "none recorded".into();
    }
    format!(
        "p50 {:.2} ms, p99 {:.2} ms (n = {})",
        ms(h.value_at_quantile(0.5)),
        ms(h.value_at_quantile(0.99)),
        h.len()
    )
}

/// The rig the demo runs: the example rig of simulated devices (`binocular`: the binocular
/// example rig), in `mode`, at `size` pixels (light field at a 30 Hz display: its frames are
/// slow on the CPU).
pub fn demo_config(mode: Mode, size: usize, auto: bool, binocular: bool) -> Result<RigConfig> {
    let rig_mode = frames::rig_mode(mode);
    let method = if auto {
        "auto"
    } else {
        dioptra_sched::RenderMethod::default_for(mode).as_str()
    };
    let mut text = if binocular {
        EXAMPLE_SIM_BINOCULAR_RIG
    } else {
        EXAMPLE_SIM_RIG
    }
    .to_string();
    let mut edit = |from: &str, to: String| -> Result<()> {
        if !text.contains(from) {
            bail!("the example rig config no longer has `{from}`");
        }
        text = text.replacen(from, &to, 1);
        Ok(())
    };
    edit(
        "mode = \"varifocal\"",
        format!("mode = \"{}\"", rig_mode.as_str()),
    )?;
    edit("method = \"gather\"", format!("method = \"{method}\""))?;
    edit("width = 96", format!("width = {size}"))?;
    edit("height = 96", format!("height = {size}"))?;
    if mode == Mode::LightField {
        edit("frame_hz = 60.0", "frame_hz = 30.0".into())?;
    }
    let mut cfg = RigConfig::parse(&text).context("the demo's rig config")?;
    // The demo's figures are the CPU's, whatever GPU the machine has.
    cfg.render.backend = dioptra_rig::config::RenderBackend::Cpu;
    Ok(cfg)
}

fn summary(r: &Run, mode: Mode) {
    let st = r.status;
    let c = st.counters;
    let l = &r.latency;
    println!("\n== loop ==");
    println!(
        "gaze samples {}, saccades {}, blinks {}",
        c.gaze_samples, c.saccades, c.blinks
    );
    if mode == Mode::Varifocal {
        println!("lens commands {}", c.lens_commands);
        println!(
            "gaze-to-focus latency (tracker exposure to lens settled): {}",
            p50_p99(l.stage(Stage::GazeToSettled))
        );
        println!(
            "lens settle (command on the wire to settled readback): {}",
            p50_p99(l.stage(Stage::WireToSettled))
        );
        match (
            percentile(&r.log.host_path, 50.0),
            percentile(&r.log.host_path, 99.0),
        ) {
            (Some(a), Some(b)) => println!(
                "host path, gaze sample received to lens command written (wall clock on this machine, the rig runtime's path): p50 {:.1} µs, p99 {:.1} µs (n = {})",
                a.as_secs_f64() * 1e6,
                b.as_secs_f64() * 1e6,
                r.log.host_path.len()
            ),
            _ => println!("host path: no gaze-caused lens command"),
        }
    }
    println!(
        "tracker to host, after the driver's clock mapping (one-way evidence cannot see the constant part of the delay): {}",
        p50_p99(l.stage(Stage::TrackerToHost))
    );
    println!(
        "gaze sample to display: {}",
        p50_p99(l.stage(Stage::GazeToDisplay))
    );
    println!(
        "frames: requested {}, rendered {}, presented {}, deadline misses {} (frame shown again), late {}, slots skipped while rendering {}",
        c.frames_requested,
        c.frames_rendered,
        c.frames_presented,
        c.misses,
        c.late_frames,
        c.renders_skipped
    );
    if mode == Mode::Multifocal {
        println!(
            "sync board: {} events, {} faults",
            r.log.sequencer_events, c.sequencer_faults
        );
    }
    for (method, h) in l.render_by_method() {
        println!(
            "render time, {} (CPU, wall clock on this machine): {}",
            method.as_str(),
            p50_p99(h)
        );
    }
}

/// The probe nearest `t`.
fn probe_at(r: &Run, t: Timestamp) -> Option<&dioptra_rig::simulated_rig::Probe> {
    r.log
        .probes
        .iter()
        .min_by_key(|p| p.t.signed_diff_ns(t).unsigned_abs())
}

/// Scores the kept frames: what the eye sees against a thin-lens render of the same scene
/// at the eye's accommodation.
fn score(r: &Run, frames: &DemoFrames, kept: &[Kept], args: &Args) -> Result<()> {
    println!(
        "\n== accuracy: what the eye sees vs thin-lens ground truth ({} rays/pixel) ==",
        args.truth_samples
    );
    if kept.is_empty() {
        println!("no frame was kept for scoring (the run was too short)");
        return Ok(());
    }
    for (i, k) in kept.iter().take(args.scored).enumerate() {
        let started = Instant::now();
        // The eye accommodates to its vergence; the lens is wherever it really was.
        let Some(p) = probe_at(r, k.display_time) else {
            continue;
        };
        let accommodation = Diopters(p.vergence_d.unwrap_or(1.0).max(0.0) as f32);
        // Only a varifocal display moves its lens with gaze; the display's image is where
        // the simulated lens puts it through the simulated optics.
        let lens = p.eye_focus.filter(|_| frames.mode() == Mode::Varifocal);
        let eye_img = frames.eye_view(k, accommodation, lens)?;
        let truth = frames.ground_truth(k, accommodation, args.truth_samples)?;
        let q = metrics::quality(&eye_img, &truth, None)?;
        let base = args.out.join(format!("frame_{i}"));
        write(&base, "input", &k.input.color)?;
        for (name, img) in frames.rendered_images(k) {
            write(&base, &name, &img)?;
        }
        write(&base, "eye", &eye_img)?;
        write(&base, "truth", &truth)?;
        println!(
            "frame {} at {:.2} s: eye focused at {:.2} D{}: PSNR {:.2} dB, SSIM {:.4} ({:.1} s to score)",
            k.frame,
            k.display_time.as_secs_f64(),
            accommodation.0,
            lens.map_or(String::new(), |l| format!(", lens at {:.2} D", l.0)),
            q.psnr,
            q.ssim,
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

fn write(base: &Path, what: &str, img: &RgbImage) -> Result<()> {
    let path = PathBuf::from(format!("{}_{what}.png", base.display()));
    dioptra_render::io::write_color(&path, img)
        .with_context(|| format!("cannot write {}", path.display()))
}
