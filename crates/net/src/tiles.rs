//! The tiles a refinement net runs on: shared by the inference engines ([`crate::cpu`],
//! [`crate::gpu`]) and the refinement that decides them ([`crate::refine`]).

use dioptra_core::Plane;

/// Side of an error-map tile, pixels (a multiple of every interleave rate).
pub const TILE: usize = 16;

/// Which tiles of an image the refinement net runs on, and which of their pixels take its
/// correction.
#[derive(Debug, Clone, PartialEq)]
pub struct TileMap {
    pub width: usize,
    pub height: usize,
    /// Tiles per row and per column.
    pub cols: usize,
    pub rows: usize,
    /// Row-major, `rows * cols`.
    pub on: Vec<bool>,
    /// Per pixel, row-major: whether the correction applies (always inside a tile that runs).
    /// A pixel a single view already sees right (a sharp occluder's own pixels beside a
    /// blurred background, a sharp pixel beside a blurred occluder, any pixel blurred by less
    /// than [`crate::refine::MIN_OWN_BLUR_PX`]) keeps the classical value even inside a tile.
    pub pixels: Vec<bool>,
    /// Per pixel: whether a blurred depth step's disk reaches it (every corrected pixel is).
    /// The others keep no light-field value: depth is smooth within their blur, so
    /// [`dioptra_render::gather::gather_smooth`] computes what gather would, without the light field's sampling of
    /// the pupil (see [`crate::refine::classical_composite`]).
    pub reached: Vec<bool>,
}

impl TileMap {
    pub fn none(width: usize, height: usize) -> TileMap {
        let (cols, rows) = (width.div_ceil(TILE), height.div_ceil(TILE));
        TileMap {
            width,
            height,
            cols,
            rows,
            on: vec![false; cols * rows],
            pixels: vec![false; width * height],
            reached: vec![false; width * height],
        }
    }

    /// The tiles holding a pixel of `pixels` (row-major, `width * height`), which are the
    /// pixels corrected and reached.
    pub fn from_pixels(width: usize, height: usize, pixels: Vec<bool>) -> TileMap {
        let mut map = TileMap::none(width, height);
        for (y, row) in pixels.chunks(width.max(1)).enumerate() {
            for (tx, tile) in row.chunks(TILE).enumerate() {
                if tile.contains(&true) {
                    map.on[(y / TILE) * map.cols + tx] = true;
                }
            }
        }
        map.reached.clone_from(&pixels);
        map.pixels = pixels;
        map
    }

    pub fn all(width: usize, height: usize) -> TileMap {
        let mut t = TileMap::none(width, height);
        t.on.fill(true);
        t.pixels.fill(true);
        t.reached.fill(true);
        t
    }

    /// The fraction of tiles run.
    pub fn fraction(&self) -> f64 {
        if self.on.is_empty() {
            return 0.0;
        }
        self.on.iter().filter(|&&b| b).count() as f64 / self.on.len() as f64
    }

    /// Whether pixel `(x, y)` lies in a tile that runs.
    pub fn covers(&self, x: usize, y: usize) -> bool {
        self.on
            .get((y / TILE) * self.cols + x / TILE)
            .copied()
            .unwrap_or(false)
    }

    /// Whether pixel `(x, y)` takes the net's correction.
    pub fn corrects(&self, x: usize, y: usize) -> bool {
        x < self.width
            && self
                .pixels
                .get(y * self.width + x)
                .copied()
                .unwrap_or(false)
    }

    /// 1 on the pixels of tiles that run, 0 elsewhere.
    pub fn mask(&self) -> Plane {
        let data = (0..self.width * self.height)
            .map(|i| f32::from(u8::from(self.covers(i % self.width, i / self.width))))
            .collect();
        Plane::from_vec(self.width, self.height, data)
            .unwrap_or_else(|_| Plane::new(self.width, self.height, 0.0))
    }
}
