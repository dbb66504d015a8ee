//! The eyepiece's distortion and lateral chromatic aberration: OpenCV's camera model
//! (Brown-Conrady radial and tangential terms with the rational k4-k6, exactly as
//! `cv2.projectPoints` applies them), one per colour channel.
//!
//! The eye is the camera and the panel is its image: a direction from the eye's pupil,
//! written as the tangents of its angles `(x, y) = (tan θx, tan θy)` (x right, y down, as
//! OpenCV's), is seen on panel pixel
//!
//! ```text
//! r² = x² + y²
//! R  = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
//! x' = x R + 2 p1 x y + p2 (r² + 2 x²)
//! y' = y R + p1 (r² + 2 y²) + 2 p2 x y
//! u  = fx x' + cx,   v = fy y' + cy
//! ```
//!
//! in panel pixels with OpenCV's convention: pixel (i, j)'s centre is at (i, j), so a panel
//! `W` wide spans -0.5 to W - 0.5. Each channel has its own model (lateral colour is a
//! different magnification, `fx`, or different radial terms per channel). [`ChannelModel::project`]
//! is that map; [`ChannelModel::unproject`] its inverse (panel pixel to direction, as
//! `cv2.undistortPoints` gives it without `P`, but iterated to convergence: OpenCV stops after
//! five fixed-point steps by default).
//!
//! Pre-warping: the renderer draws the ideal image, in which direction `(x, y)` is at
//! `(fx x + cx, fy y + cy)` with [`EyepieceModel::render`]'s intrinsics. The panel pixel `u`
//! of channel `c` must show what the eye sees there, the ideal image at
//! `render(unproject_c(u))`; the mesh that does this is built once (dioptra-render's `warp`).

/// A setting the model cannot use, naming its key as rig.toml spells it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct DistortionError {
    pub key: String,
    pub message: String,
}

/// A pinhole camera's intrinsics, panel pixels (OpenCV's camera matrix without skew).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Direction (tangents) to pixel.
    pub fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        (self.fx * x + self.cx, self.fy * y + self.cy)
    }
    /// Pixel to direction (tangents).
    pub fn to_direction(&self, u: f64, v: f64) -> (f64, f64) {
        ((u - self.cx) / self.fx, (v - self.cy) / self.fy)
    }
}

/// OpenCV's distortion coefficients (its order: k1, k2, p1, p2, k3, k4, k5, k6).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Coefficients {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
    pub k4: f64,
    pub k5: f64,
    pub k6: f64,
}

impl Coefficients {
    /// In OpenCV's order (its `distCoeffs` vector of 8).
    pub fn opencv_order(&self) -> [f64; 8] {
        [
            self.k1, self.k2, self.p1, self.p2, self.k3, self.k4, self.k5, self.k6,
        ]
    }

    /// The radial factor `R(r²)` and its derivative in `r²`.
    fn radial(&self, r2: f64) -> (f64, f64) {
        let n = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d = 1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6));
        let dn = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let dd = self.k4 + r2 * (2.0 * self.k5 + 3.0 * r2 * self.k6);
        (n / d, (dn * d - n * dd) / (d * d))
    }

    /// Undistorted normalised coordinates to distorted ones, and the map's Jacobian
    /// `[[dx'/dx, dx'/dy], [dy'/dx, dy'/dy]]`.
    fn distort(&self, x: f64, y: f64) -> ((f64, f64), [[f64; 2]; 2]) {
        let r2 = x * x + y * y;
        let (r, dr) = self.radial(r2);
        let (p1, p2) = (self.p1, self.p2);
        let xd = x * r + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * r + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let cross = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
        let j = [
            [r + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x, cross],
            [cross, r + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x],
        ];
        ((xd, yd), j)
    }

    /// Whether the radial map stops growing anywhere from the axis out to radius `r`
    /// (checked at 64 radii: a fold narrower than `r / 64` that unfolds again is missed,
    /// which no lens's smooth distortion has).
    fn folds_within(&self, r: f64) -> bool {
        (1..=64).any(|i| {
            let q = r * f64::from(i) / 64.0;
            let (rr, dr) = self.radial(q * q);
            let slope = rr + 2.0 * q * q * dr;
            slope.is_nan() || slope <= 0.0 || !rr.is_finite()
        })
    }

    /// The radius (in tangent units) where the radial map `r R(r²)` stops growing, if it does
    /// before `limit`: beyond it two directions land on one pixel and the model has no
    /// inverse. Scanned in steps of 1e-4 (a radius known to that).
    pub fn fold_radius(&self, limit: f64) -> Option<f64> {
        let steps = (limit / 1e-4).ceil() as usize;
        (0..=steps).map(|i| i as f64 * 1e-4).find(|&r| {
            let (rr, dr) = self.radial(r * r);
            // d/dr (r R(r²)) = R + 2 r² R'; a pole of the rational term also ends it.
            let slope = rr + 2.0 * r * r * dr;
            slope.is_nan() || slope <= 0.0 || !rr.is_finite()
        })
    }
}

/// One colour channel's model: its camera and its distortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelModel {
    pub camera: Intrinsics,
    pub coefficients: Coefficients,
}

/// Largest distance from the axis, in tangent units (84 degrees), a direction may have.
pub const MAX_TANGENT: f64 = 10.0;

impl ChannelModel {
    /// Eye direction (tangents) to panel pixel: `cv2.projectPoints` of the point (x, y, 1)
    /// with no rotation or translation.
    pub fn project(&self, x: f64, y: f64) -> (f64, f64) {
        let ((xd, yd), _) = self.coefficients.distort(x, y);
        self.camera.to_pixel(xd, yd)
    }

    /// Panel pixel to eye direction (tangents): the inverse of [`ChannelModel::project`],
    /// solved by Newton's method from OpenCV's first guess until the pixel is reproduced to
    /// 1e-9 px. `None` where there is no inverse on the model's unfolded side: beyond the
    /// fold (see [`Coefficients::fold_radius`]) or where the map turns over.
    pub fn unproject(&self, u: f64, v: f64) -> Option<(f64, f64)> {
        let (tx, ty) = self.camera.to_direction(u, v);
        if !(tx.is_finite() && ty.is_finite()) {
            return None;
        }
        let c = &self.coefficients;
        // OpenCV's first guess is the distorted point itself.
        let (mut x, mut y) = (tx, ty);
        let tol = 1e-9 / self.camera.fx.abs().max(self.camera.fy.abs()).max(1.0);
        for _ in 0..100 {
            let ((xd, yd), j) = c.distort(x, y);
            let (ex, ey) = (xd - tx, yd - ty);
            let err = ex.abs().max(ey.abs());
            if !err.is_finite() {
                return None;
            }
            if err < tol {
                let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
                let r = (x * x + y * y).sqrt();
                return (det > 0.0 && !c.folds_within(r) && r <= MAX_TANGENT).then_some((x, y));
            }
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if det.abs() < 1e-300 {
                return None;
            }
            let dx = (j[1][1] * ex - j[0][1] * ey) / det;
            let dy = (j[0][0] * ey - j[1][0] * ex) / det;
            // Damped: halve a step that does not reduce the error (away from the fold a full
            // Newton step always does).
            let mut s = 1.0;
            loop {
                let (nx, ny) = (x - s * dx, y - s * dy);
                let ((nxd, nyd), _) = c.distort(nx, ny);
                let nerr = (nxd - tx).abs().max((nyd - ty).abs());
                if nerr < err || s < 1e-6 {
                    x = nx;
                    y = ny;
                    break;
                }
                s *= 0.5;
            }
            if x.abs() > 2.0 * MAX_TANGENT || y.abs() > 2.0 * MAX_TANGENT {
                return None;
            }
        }
        None
    }
}

/// Colour channels in panel order.
pub const CHANNELS: [&str; 3] = ["red", "green", "blue"];

/// An eyepiece: the ideal image's intrinsics and a model per colour channel.
#[derive(Debug, Clone, PartialEq)]
pub struct EyepieceModel {
    /// Where the renderer's ideal image puts a direction: the image the pre-warp starts from.
    pub render: Intrinsics,
    /// Red, green, blue.
    pub channels: [ChannelModel; 3],
}

impl EyepieceModel {
    /// A model with the same intrinsics for the render and every channel, and one set of
    /// coefficients per channel. Checked as [`EyepieceModel::checked`] does.
    pub fn new(
        camera: Intrinsics,
        coefficients: [Coefficients; 3],
    ) -> Result<Self, DistortionError> {
        EyepieceModel {
            render: camera,
            channels: coefficients.map(|coefficients| ChannelModel {
                camera,
                coefficients,
            }),
        }
        .checked("distortion")
    }

    /// No distortion: every channel is the render camera.
    pub fn identity(camera: Intrinsics) -> Self {
        let ch = ChannelModel {
            camera,
            coefficients: Coefficients::default(),
        };
        EyepieceModel {
            render: camera,
            channels: [ch; 3],
        }
    }

    /// Checks every number; `section` prefixes the keys in messages (e.g.
    /// `optics.distortion`).
    pub fn checked(self, section: &str) -> Result<Self, DistortionError> {
        let bad = |key: String, message: String| DistortionError { key, message };
        let cam = |c: &Intrinsics, at: &str| -> Result<(), DistortionError> {
            for (name, v, positive) in [
                ("fx", c.fx, true),
                ("fy", c.fy, true),
                ("cx", c.cx, false),
                ("cy", c.cy, false),
            ] {
                if !v.is_finite() || (positive && v <= 0.0) || v.abs() > 1e7 {
                    return Err(bad(
                        format!("{at}.{name}"),
                        format!(
                            "{v}: expected {} (panel pixels)",
                            if positive {
                                "a focal length above 0"
                            } else {
                                "the optical centre's coordinate"
                            }
                        ),
                    ));
                }
            }
            Ok(())
        };
        cam(&self.render, section)?;
        for (ch, name) in self.channels.iter().zip(CHANNELS) {
            let at = format!("{section}.{name}");
            cam(&ch.camera, &at)?;
            let c = &ch.coefficients;
            for (k, v) in ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
                .iter()
                .zip(c.opencv_order())
            {
                if !v.is_finite() || v.abs() > 1e4 {
                    return Err(bad(
                        format!("{at}.{k}"),
                        format!("{v}: expected a coefficient of OpenCV's model (|v| < 1e4)"),
                    ));
                }
            }
        }
        Ok(self)
    }

    /// Whether every channel is the render camera with no distortion.
    pub fn is_identity(&self) -> bool {
        self.channels
            .iter()
            .all(|c| c.camera == self.render && c.coefficients == Coefficients::default())
    }
}

/// `[optics.distortion]` as rig.toml (and `dioptra optics --distortion FILE`) spells it: the
/// render intrinsics and the coefficients shared by every channel (0 when absent), each
/// channel's table overriding any of them.
#[cfg(feature = "serde")]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DistortionSection {
    /// Only "opencv" (the default): the model above.
    #[serde(default)]
    pub model: DistortionKind,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: Option<f64>,
    pub k2: Option<f64>,
    pub p1: Option<f64>,
    pub p2: Option<f64>,
    pub k3: Option<f64>,
    pub k4: Option<f64>,
    pub k5: Option<f64>,
    pub k6: Option<f64>,
    pub red: Option<ChannelKeys>,
    pub green: Option<ChannelKeys>,
    pub blue: Option<ChannelKeys>,
}

/// The models `[optics.distortion] model` names.
#[cfg(feature = "serde")]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DistortionKind {
    #[default]
    Opencv,
}

/// `[optics.distortion.red|green|blue]`: any intrinsic or coefficient of that channel.
#[cfg(feature = "serde")]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelKeys {
    pub fx: Option<f64>,
    pub fy: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    pub k1: Option<f64>,
    pub k2: Option<f64>,
    pub p1: Option<f64>,
    pub p2: Option<f64>,
    pub k3: Option<f64>,
    pub k4: Option<f64>,
    pub k5: Option<f64>,
    pub k6: Option<f64>,
}

#[cfg(feature = "serde")]
impl DistortionSection {
    /// The model, checked; `section` is where it was read (`optics.distortion`,
    /// `optics.left.distortion`) for messages.
    pub fn model(&self, section: &str) -> Result<EyepieceModel, DistortionError> {
        let render = Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        };
        let z = |v: Option<f64>| v.unwrap_or(0.0);
        let shared = Coefficients {
            k1: z(self.k1),
            k2: z(self.k2),
            p1: z(self.p1),
            p2: z(self.p2),
            k3: z(self.k3),
            k4: z(self.k4),
            k5: z(self.k5),
            k6: z(self.k6),
        };
        let channel = |keys: &Option<ChannelKeys>| {
            let k = keys.unwrap_or_default();
            ChannelModel {
                camera: Intrinsics {
                    fx: k.fx.unwrap_or(render.fx),
                    fy: k.fy.unwrap_or(render.fy),
                    cx: k.cx.unwrap_or(render.cx),
                    cy: k.cy.unwrap_or(render.cy),
                },
                coefficients: Coefficients {
                    k1: k.k1.unwrap_or(shared.k1),
                    k2: k.k2.unwrap_or(shared.k2),
                    p1: k.p1.unwrap_or(shared.p1),
                    p2: k.p2.unwrap_or(shared.p2),
                    k3: k.k3.unwrap_or(shared.k3),
                    k4: k.k4.unwrap_or(shared.k4),
                    k5: k.k5.unwrap_or(shared.k5),
                    k6: k.k6.unwrap_or(shared.k6),
                },
            }
        };
        EyepieceModel {
            render,
            channels: [
                channel(&self.red),
                channel(&self.green),
                channel(&self.blue),
            ],
        }
        .checked(section)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn barrel() -> ChannelModel {
        ChannelModel {
            camera: Intrinsics {
                fx: 900.0,
                fy: 905.0,
                cx: 959.5,
                cy: 539.5,
            },
            coefficients: Coefficients {
                k1: 0.22,
                k2: 0.05,
                p1: 0.001,
                p2: -0.0015,
                k3: 0.01,
                k4: 0.02,
                k5: 0.0,
                k6: 0.001,
            },
        }
    }

    #[test]
    fn a_hand_computed_point_projects_where_the_formula_puts_it() {
        // x = 0.3, y = -0.2 by hand: r² = 0.13, N = 1 + 0.22*0.13 + 0.05*0.0169 + 0.01*0.002197
        // = 1.02946697, D = 1 + 0.02*0.13 + 0.001*0.002197 = 1.002602197,
        // R = 1.026795..., x' = 0.3 R + 2*0.001*0.3*(-0.2) - 0.0015*(0.13 + 0.18),
        // y' = -0.2 R + 0.001*(0.13 + 0.08) + 2*(-0.0015)*0.3*(-0.2).
        let m = barrel();
        let r = 1.029_466_97 / 1.002_602_197;
        let xd = 0.3 * r - 0.000_12 - 0.000_465;
        let yd = -0.2 * r + 0.000_21 + 0.000_18;
        let (u, v) = m.project(0.3, -0.2);
        assert!((u - (900.0 * xd + 959.5)).abs() < 1e-9, "{u}");
        assert!((v - (905.0 * yd + 539.5)).abs() < 1e-9, "{v}");
    }

    #[test]
    fn unproject_inverts_project_over_a_1080p_panel() {
        let m = barrel();
        let mut worst = 0.0f64;
        for j in 0..=27 {
            for i in 0..=48 {
                let (u, v) = (-0.5 + 40.0 * i as f64, -0.5 + 40.0 * j as f64);
                let (x, y) = m.unproject(u, v).expect("inside the field");
                let (u2, v2) = m.project(x, y);
                worst = worst.max((u2 - u).abs().max((v2 - v).abs()));
            }
        }
        assert!(worst < 1e-8, "round trip off by {worst} px");
    }

    #[test]
    fn beyond_the_fold_there_is_no_inverse() {
        // Strong negative k1: r (1 - 0.5 r²) peaks at r = 0.816, where it reaches 0.544.
        let m = ChannelModel {
            camera: Intrinsics {
                fx: 100.0,
                fy: 100.0,
                cx: 0.0,
                cy: 0.0,
            },
            coefficients: Coefficients {
                k1: -0.5,
                ..Default::default()
            },
        };
        let fold = m.coefficients.fold_radius(5.0).unwrap();
        assert!((fold - (1.0f64 / 1.5).sqrt()).abs() < 2e-4, "{fold}");
        // Inside the peak's image: found, on the near side of the fold.
        let (x, _) = m.unproject(50.0, 0.0).unwrap();
        assert!(x < fold && (m.project(x, 0.0).0 - 50.0).abs() < 1e-9);
        // Beyond what the model can reach: none.
        assert!(m.unproject(60.0, 0.0).is_none());
    }

    #[test]
    fn bad_numbers_are_refused_naming_the_key() {
        let cam = Intrinsics {
            fx: 900.0,
            fy: 900.0,
            cx: 0.0,
            cy: 0.0,
        };
        let mut c = [Coefficients::default(); 3];
        c[2].k2 = f64::NAN;
        let e = EyepieceModel::new(cam, c).unwrap_err().to_string();
        assert!(e.contains("distortion.blue.k2"), "{e}");
        let e = EyepieceModel::new(Intrinsics { fx: 0.0, ..cam }, [Coefficients::default(); 3])
            .unwrap_err()
            .to_string();
        assert!(e.contains("distortion.fx"), "{e}");
    }
}
