//! Each eye's image as its panel is driven: scaled about the optical axis by the frame's
//! magnification compensation, pre-warped for the eyepiece (per colour channel), and encoded
//! through the panel's transfer function ([`PanelImage`], built once per eye from
//! [`crate::config::EyeImage`]). The headless sink runs the CPU twins here
//! (`dioptra_render::warp::warp_cpu` with the encoding inside it); the window draws the same
//! mesh and table on the GPU (`warp::gpu::WarpPipeline`, in [`super::panel_draw`]).

use dioptra_core::transfer::Transfer;
use dioptra_core::{RgbImage, Side};
use dioptra_render::transfer::EncodeLut;
use dioptra_render::warp::{warp_cpu, WarpDraw, WarpMesh, DEFAULT_STEP_PX};
use dioptra_render::RenderError;
use serde_json::{json, Value};

use crate::config::EyeImage;

/// One eye's way from the renderer's linear image to its panel's code values.
#[derive(Debug, Clone)]
pub struct PanelImage {
    pub eye: Option<Side>,
    /// The pre-warp (an identity mesh when only the magnification is compensated); `None`:
    /// drawn 1:1.
    mesh: Option<WarpMesh>,
    /// Where the eyepiece's model was read; `None`: no distortion.
    distortion: Option<String>,
    /// The magnification is compensated (the frame carries the factor).
    compensate: bool,
    transfer: Transfer,
    transfer_key: &'static str,
    lut: EncodeLut,
    /// The eye's image (width, height): the display's.
    size: [usize; 2],
}

impl PanelImage {
    /// The eye's image path for images of `size` (width, height: the display's, one eye's).
    /// Building the mesh takes about 0.5 s at 1080p (once, at start).
    pub fn new(image: &EyeImage, size: [usize; 2]) -> Result<PanelImage, RenderError> {
        let compensate = image.reference.is_some();
        let mesh = match &image.eyepiece {
            Some(e) => Some(WarpMesh::new(&e.model, size, size, DEFAULT_STEP_PX)?),
            None if compensate => Some(WarpMesh::identity(
                size,
                size,
                [(size[0] as f64 - 1.0) / 2.0, (size[1] as f64 - 1.0) / 2.0],
            )?),
            None => None,
        };
        Ok(PanelImage {
            eye: image.eye,
            mesh,
            distortion: image.eyepiece.as_ref().map(|e| e.from.clone()),
            compensate,
            lut: EncodeLut::new(&image.transfer),
            transfer: image.transfer.clone(),
            transfer_key: image.transfer_key,
            size,
        })
    }

    /// Whether the image is changed on its way to the panel beyond what a plain sRGB PNG
    /// writes: warped, scaled or encoded for another transfer function.
    pub fn changes_image(&self) -> bool {
        self.mesh.is_some() || self.transfer != Transfer::Srgb
    }

    /// The mesh the window's GPU pass draws (`None`: 1:1).
    pub fn mesh(&self) -> Option<&WarpMesh> {
        self.mesh.as_ref()
    }

    /// The mesh a GPU pass draws: [`PanelImage::mesh`], or where the image is only encoded,
    /// one that copies it (the window draws every eye's image through the warp pipeline).
    pub fn mesh_to_draw(&self) -> Result<std::borrow::Cow<'_, WarpMesh>, RenderError> {
        match &self.mesh {
            Some(m) => Ok(std::borrow::Cow::Borrowed(m)),
            None => {
                let centre = self.size.map(|n| (n as f64 - 1.0) / 2.0);
                WarpMesh::identity(self.size, self.size, centre).map(std::borrow::Cow::Owned)
            }
        }
    }

    /// The eye's image size (width, height) this path is made for.
    pub fn size(&self) -> [usize; 2] {
        self.size
    }

    /// The panel's transfer table (both twins read it).
    pub fn lut(&self) -> &EncodeLut {
        &self.lut
    }

    /// The warp's scale for a frame's compensation factor `c` (the image drawn `c` times its
    /// size: read from `1 / c` times as far out); 1 without compensation.
    pub fn scale_for(&self, compensation: Option<f32>) -> f32 {
        match (self.compensate, compensation) {
            (true, Some(c)) if c.is_finite() && c > 0.0 => 1.0 / c,
            _ => 1.0,
        }
    }

    /// The CPU twin: the eye's linear `image` as its panel's code values (0 to 1), scaled for
    /// the frame's compensation factor, pre-warped and encoded.
    pub fn to_panel(
        &self,
        image: &RgbImage,
        compensation: Option<f32>,
    ) -> Result<RgbImage, RenderError> {
        match &self.mesh {
            Some(mesh) => warp_cpu(
                image,
                mesh,
                &WarpDraw {
                    scale: self.scale_for(compensation),
                    encode: Some(&self.lut),
                },
            ),
            None => Ok(self.lut.encode_image(image)),
        }
    }

    /// `/status`: the compensation (with the newest factor), the distortion, the transfer.
    pub fn status(&self, compensation: Option<f32>) -> Value {
        json!({
            "compensate_magnification": self.compensate,
            "size_compensation": if self.compensate { compensation } else { None },
            "distortion": self.distortion.is_some(),
            "distortion_from": self.distortion,
            "pre_warp_vertices": self.mesh.as_ref().filter(|_| self.distortion.is_some()).map(|m| m.vertices().len()),
            "transfer": self.transfer.describe(),
            "transfer_key": self.transfer_key,
        })
    }
}
