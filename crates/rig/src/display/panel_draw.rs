//! What a window draws on one output, on the GPU: each placed eye's image and the marker
//! patch. Without image corrections the images go through the blit ([`super::blit`]: drawn
//! 1:1, encoded sRGB by the target's sRGB view). With them (`[optics]` compensation or
//! distortion, a `display.transfer` other than sRGB: [`super::panel_images`] is not empty),
//! each eye's image goes through the GPU twin of [`PanelImage::to_panel`]: the warp pipeline
//! of `dioptra_render` (`shaders/warp.wgsl` with `transfer_lut.wgsl`) draws it through the
//! eye's pre-warp mesh, per colour channel, read `1 / compensation` as far out about the
//! optical centre, and encodes it through the panel's transfer table, at the rectangle
//! [`super::placement`] gives, into a non-sRGB view (code values written as they are). That is
//! what the headless sink composes on the CPU ([`PanelImage::to_panel`], then
//! [`super::placement::draw_into`] and [`super::MarkerDraw::paint`]), and a test holds the two
//! to one 8-bit step.
//!
//! Made once per output: the blit, the warp pipeline, a mesh and a table per eye in GPU
//! memory. A frame in the window's GPU memory is read where it is; one on the host (the rig
//! renders on the CPU) is uploaded into a pooled buffer, which later frames reuse.

use std::sync::Arc;

use dioptra_render::gpu::{GpuContext, GpuImage};
use dioptra_render::transfer::gpu::{upload_image, GpuEncodeLut};
use dioptra_render::warp::gpu::{GpuWarpMesh, WarpPipeline};

use super::blit::{set_rect, Blit};
use super::placement::{PlaceError, Placed, Rect};
use super::{MarkerDraw, PanelImage};
use crate::render::FrameImage;

/// Why an image is not drawn.
#[derive(Debug)]
pub enum DrawError {
    /// This frame's image cannot be shown (counted and logged as a misfit is).
    Refused(PlaceError),
    /// The GPU failed.
    Gpu(String),
}

impl std::fmt::Display for DrawError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DrawError::Refused(e) => e.fmt(f),
            DrawError::Gpu(e) => f.write_str(e),
        }
    }
}

/// One eye's corrections on the GPU.
struct EyePass {
    panel: PanelImage,
    mesh: GpuWarpMesh,
    lut: GpuEncodeLut,
}

/// The image corrections: the warp pipeline for the target's format, and each eye's pass.
struct Corrections {
    pipeline: WarpPipeline,
    eyes: Vec<EyePass>,
}

/// An image made ready to draw by [`PanelDraw::prepare`].
pub struct Prepared {
    rect: Rect,
    how: How,
}

enum How {
    /// Through the blit's slot.
    Blit(usize),
    /// Through eye pass `eye`'s mesh and table, from `source`, at warp scale `scale`.
    Corrected {
        eye: usize,
        source: GpuImage,
        scale: f32,
    },
}

/// What one output draws; see the module doc.
pub struct PanelDraw {
    blit: Blit,
    /// The GPU context frames in GPU memory are read from without a copy (the render's, or the
    /// one the corrections run on).
    ctx: Option<Arc<GpuContext>>,
    corrections: Option<Corrections>,
}

impl PanelDraw {
    /// Draws into views of `target_format` on `device`. With `panels` (each eye's corrections,
    /// not empty) the images are corrected on `ctx`'s device, which must be `device`, and
    /// `target_format` must not be sRGB (the transfer table writes the code values). Frames
    /// in `ctx`'s GPU memory are drawn without a copy.
    pub fn new(
        device: &wgpu::Device,
        target_format: wgpu::TextureFormat,
        ctx: Option<Arc<GpuContext>>,
        panels: &[PanelImage],
    ) -> Result<PanelDraw, String> {
        let corrections = if panels.is_empty() {
            None
        } else {
            let Some(ctx) = ctx.as_ref().filter(|c| c.device() == device) else {
                return Err(
                    "the eyes' image corrections are drawn on the GPU context the window draws \
                     with, and none was given"
                        .into(),
                );
            };
            if target_format.is_srgb() {
                return Err(format!(
                    "the eyes' image corrections write the panel's code values: a view of \
                     {target_format:?} would encode them again"
                ));
            }
            let eyes = panels
                .iter()
                .map(|p| {
                    let mesh = p
                        .mesh_to_draw()
                        .map_err(|e| format!("the pre-warp mesh: {e}"))?;
                    Ok(EyePass {
                        mesh: GpuWarpMesh::new(ctx, &mesh),
                        lut: GpuEncodeLut::new(ctx, p.lut())
                            .map_err(|e| format!("the transfer table: {e}"))?,
                        panel: p.clone(),
                    })
                })
                .collect::<Result<Vec<_>, String>>()?;
            Some(Corrections {
                pipeline: WarpPipeline::new(ctx, target_format),
                eyes,
            })
        };
        Ok(PanelDraw {
            blit: Blit::new(device, target_format),
            ctx,
            corrections,
        })
    }

    /// Whether the images are corrected (drawn as code values).
    pub fn corrects(&self) -> bool {
        self.corrections.is_some()
    }

    /// The marker patch the next draws show over the frame (`None`: none).
    pub fn set_marker(&mut self, marker: Option<MarkerDraw>) {
        self.blit.set_marker(marker);
    }

    /// Makes `placed` ready to draw as the `slot`th image (0 or 1) of the next
    /// [`PanelDraw::encode`], the frame's magnification compensation for its eye being
    /// `compensation`. A frame in another device's memory is read back first.
    pub fn prepare(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        slot: usize,
        placed: &Placed,
        compensation: Option<f32>,
    ) -> Result<Prepared, DrawError> {
        let gpu = |e: &dyn std::fmt::Display| DrawError::Gpu(e.to_string());
        let on_ctx = |g: &GpuImage| {
            self.ctx
                .as_ref()
                .is_some_and(|c| Arc::ptr_eq(c, g.context()))
        };
        let Some(c) = &self.corrections else {
            match placed.image {
                FrameImage::Host(i) => self.blit.upload(device, queue, slot, i),
                FrameImage::Gpu(g) if on_ctx(g) => self.blit.show_buffer(device, queue, slot, g),
                // Another device's memory: through the host.
                FrameImage::Gpu(g) => {
                    let pixels = g
                        .read()
                        .map_err(|e| gpu(&format!("reading the frame back: {e}")))?;
                    self.blit.upload(device, queue, slot, &pixels)
                }
            }
            return Ok(Prepared {
                rect: placed.rect,
                how: How::Blit(slot),
            });
        };
        let eye = c
            .eyes
            .iter()
            .position(|e| e.panel.eye == placed.eye)
            .ok_or_else(|| {
                DrawError::Refused(PlaceError::NoImage(format!(
                    "no image corrections for the {} image",
                    placed.eye.map_or("one", |s| s.as_str())
                )))
            })?;
        let size = [placed.image.width(), placed.image.height()];
        let want = c.eyes[eye].panel.size();
        if size != want {
            return Err(DrawError::Refused(PlaceError::NoImage(format!(
                "the {} image is {}x{}; its pre-warp and transfer are made for display.width x \
                 display.height = {}x{}",
                placed.eye.map_or("one", |s| s.as_str()),
                size[0],
                size[1],
                want[0],
                want[1]
            ))));
        }
        let ctx = self
            .ctx
            .as_ref()
            .ok_or_else(|| gpu(&"no GPU context for the image corrections"))?;
        let source = match placed.image {
            FrameImage::Gpu(g) if on_ctx(g) => g.clone(),
            FrameImage::Gpu(g) => {
                let pixels = g
                    .read()
                    .map_err(|e| gpu(&format!("reading the frame back: {e}")))?;
                upload_image(ctx, &pixels).map_err(|e| gpu(&e))?
            }
            FrameImage::Host(i) => upload_image(ctx, i).map_err(|e| gpu(&e))?,
        };
        Ok(Prepared {
            rect: placed.rect,
            how: How::Corrected {
                eye,
                source,
                scale: c.eyes[eye].panel.scale_for(compensation),
            },
        })
    }

    /// Draws the `prepared` images at their rectangles into `target` (a view of the target
    /// format, `target_size`), cleared to black, and the marker patch over them.
    pub fn encode(
        &self,
        enc: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
        prepared: &[Prepared],
    ) -> Result<(), DrawError> {
        let plain: Vec<(usize, Rect)> = prepared
            .iter()
            .filter_map(|p| match p.how {
                How::Blit(slot) => Some((slot, p.rect)),
                How::Corrected { .. } => None,
            })
            .collect();
        self.blit
            .encode_with(enc, target, target_size, &plain, |pass| {
                let Some(c) = &self.corrections else {
                    return Ok(());
                };
                for p in prepared {
                    let How::Corrected { eye, source, scale } = &p.how else {
                        continue;
                    };
                    if !set_rect(pass, p.rect, target_size) {
                        continue;
                    }
                    let e = &c.eyes[*eye];
                    c.pipeline
                        .draw_in_pass(pass, source, &e.mesh, *scale, Some(&e.lut))
                        .map_err(|e| DrawError::Gpu(format!("the eye's image pass: {e}")))?;
                }
                Ok(())
            })
    }
}

#[cfg(test)]
mod tests;
