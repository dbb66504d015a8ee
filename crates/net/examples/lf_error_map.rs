//! How well the warp's error map (`dioptra_render::views::WarpErrors`, C5R's gate) finds the
//! classical light field's error on an independent set (`generate_lf.py`'s scenes): per scene,
//! over the novel views of a 9 x 9 light field from its 9 inputs, the fraction of pixels marked
//! (and by which cause), of C5R's tiles, and of the classical views' squared error (sRGB) that
//! lies on the marked pixels.
//!
//! `cargo run --release -p dioptra-net --example lf_error_map -- SET_DIR`

use dioptra_core::image::linear_to_srgb;
use dioptra_core::{EyeModel, Rgbd};
use dioptra_net::refine::view_tiles;
use dioptra_render::io::{read_color, read_depth};
use dioptra_render::views::{
    light_field_positions, synthesize_view_with_errors, RgbdView, EDGE_MIN_PX, SPREAD_MIN,
};

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn main() -> Res<()> {
    let set = std::env::args()
        .nth(1)
        .ok_or("usage: lf_error_map SET_DIR (generate_lf.py's output)")?;
    let mut dirs: Vec<_> = std::fs::read_dir(&set)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("lightfield.json").exists())
        .collect();
    dirs.sort();
    println!("| scene | marked % | hole % | edge % | spread % | tiles % | classical error on marked % | PSNR marked / unmarked |");
    println!("|---|---|---|---|---|---|---|---|");
    for dir in dirs {
        let meta: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("lightfield.json"))?)?;
        let n = meta["grid"].as_u64().ok_or("no grid")? as usize;
        let span = meta["span_m"].as_f64().ok_or("no span_m")? as f32;
        let eye = EyeModel {
            fov_horizontal_deg: meta["fov_deg"].as_f64().ok_or("no fov_deg")? as f32,
            ..EyeModel::default()
        };
        let positions = light_field_positions(n, span)?;
        let (m, e) = (n / 2, n - 1);
        let picks: Vec<usize> = [0, m, e]
            .iter()
            .flat_map(|&r| [0, m, e].map(|c| r * n + c))
            .collect();
        let view = |k: usize, ext: &str| dir.join(format!("view_{:02}_{:02}{ext}", k / n, k % n));
        let inputs = picks
            .iter()
            .map(|&k| {
                Ok(RgbdView {
                    position: positions[k],
                    rgbd: Rgbd::new(
                        read_color(&view(k, ".png"))?,
                        read_depth(&view(k, "_depth.exr"), None)?,
                    )?,
                })
            })
            .collect::<Res<Vec<_>>>()?;
        let (mut px, mut marked, mut hole, mut edge, mut spread, mut tiles) =
            (0usize, 0usize, 0usize, 0usize, 0usize, 0.0f64);
        let (mut err_on, mut err_off) = (0.0f64, 0.0f64);
        let novel: Vec<usize> = (0..n * n).filter(|k| !picks.contains(k)).collect();
        for &k in &novel {
            let (syn, map) = synthesize_view_with_errors(&inputs, positions[k], &eye)?;
            let truth = read_color(&view(k, ".pfm"))?;
            tiles += view_tiles(&map)?.fraction();
            for i in 0..map.marked.len() {
                px += 1;
                marked += usize::from(map.marked[i]);
                hole += usize::from(map.hole[i]);
                edge += usize::from(map.edge_px[i] >= EDGE_MIN_PX);
                spread += usize::from(map.spread[i] >= SPREAD_MIN);
                let e2: f64 = (0..3)
                    .map(|c| {
                        let d = linear_to_srgb(syn.color.channels[c].data()[i].clamp(0.0, 1.0))
                            - linear_to_srgb(truth.channels[c].data()[i].clamp(0.0, 1.0));
                        f64::from(d * d)
                    })
                    .sum();
                if map.marked[i] {
                    err_on += e2;
                } else {
                    err_off += e2;
                }
            }
        }
        let pct = |v: usize| 100.0 * v as f64 / px as f64;
        let psnr = |e: f64, count: usize| -10.0 * (e / (3 * count.max(1)) as f64).log10();
        println!(
            "| {} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} / {:.2} |",
            dir.file_name().and_then(|f| f.to_str()).unwrap_or("?"),
            pct(marked),
            pct(hole),
            pct(edge),
            pct(spread),
            100.0 * tiles / novel.len() as f64,
            100.0 * err_on / (err_on + err_off).max(1e-12),
            psnr(err_on, marked),
            psnr(err_off, px - marked)
        );
    }
    Ok(())
}
