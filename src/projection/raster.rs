//! Scanline rasteriser for binary masks: even-odd polygon fill with pixel-centre sampling, thick lines as quads.
//!
//! Coordinates are image coordinates in which the centre of pixel `(i, j)` (column, row) sits at `(i, j)`
//! (OpenCV / nuScenes convention, the one [`crate::scene::camera::Camera::intrinsic_scaled`] keeps). A pixel is
//! set when its centre lies inside the polygon; the half-open rule (`x_left <= i < x_right`, rows
//! `y_top <= j < y_bottom`) makes two polygons sharing an edge cover each pixel once, so the covered pixel count of
//! a polygon approximates its area.

/// A list of rings (exterior and holes, any orientation) filled together with the even-odd rule.
/// Points are `[u, v]` in image coordinates.
pub type Ring = [[f32; 2]];

/// Reusable scratch state of the scanline filler (per-row crossing lists), sized for one image size.
#[derive(Clone, Debug)]
pub struct Rasterizer {
    width: usize,
    height: usize,
    rows: Vec<Vec<f32>>,
    row_min: usize,
    row_max: usize,
}

impl Rasterizer {
    /// A rasteriser for `width x height` masks.
    pub fn new(width: usize, height: usize) -> Self {
        Rasterizer {
            width,
            height,
            rows: vec![Vec::new(); height],
            row_min: usize::MAX,
            row_max: 0,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Adds the edges of one closed ring (last point connects to the first) to the current polygon.
    pub fn add_ring(&mut self, ring: &Ring) {
        let n = ring.len();
        if n < 3 {
            return;
        }
        for k in 0..n {
            self.add_edge(ring[k], ring[(k + 1) % n]);
        }
    }

    /// Adds one edge of the current polygon: records its crossings with the pixel-centre rows it spans.
    pub fn add_edge(&mut self, a: [f32; 2], b: [f32; 2]) {
        if self.height == 0
            || !(a[1].is_finite() && b[1].is_finite() && a[0].is_finite() && b[0].is_finite())
        {
            return;
        }
        let (p, q) = if a[1] <= b[1] { (a, b) } else { (b, a) };
        if p[1] == q[1] {
            return; // horizontal edges never cross a row centre under the half-open rule
        }
        // rows j with p.y <= j < q.y
        let j0 = p[1].ceil().max(0.0);
        let j1 = (q[1].ceil() - 1.0).min(self.height as f32 - 1.0);
        if j0 > j1 {
            return;
        }
        let (j0, j1) = (j0 as usize, j1 as usize);
        let slope = (q[0] - p[0]) / (q[1] - p[1]);
        for j in j0..=j1 {
            let x = p[0] + (j as f32 - p[1]) * slope;
            self.rows[j].push(x);
        }
        self.row_min = self.row_min.min(j0);
        self.row_max = self.row_max.max(j1);
    }

    /// Fills the polygon accumulated since the last fill (even-odd rule) into `mask` (`mask: (H, W)`, row-major,
    /// set pixels become 1) and clears the scratch state. Returns the number of pixels newly or re-set.
    pub fn fill(&mut self, mask: &mut [u8]) -> usize {
        debug_assert_eq!(mask.len(), self.width * self.height);
        let w = self.width;
        self.fill_spans(|j, i0, i1| mask[j * w + i0..=j * w + i1].fill(1))
    }

    /// Like [`Rasterizer::fill`], handing each covered span to `span(row, first column, last column)`
    /// (inclusive, clipped to the image) instead of writing a mask: the same pixels as `fill`. Returns the
    /// number of pixels covered.
    pub fn fill_spans(&mut self, mut span: impl FnMut(usize, usize, usize)) -> usize {
        if self.row_min > self.row_max {
            self.row_min = usize::MAX;
            self.row_max = 0;
            return 0;
        }
        let w = self.width as f32;
        let mut count = 0;
        for j in self.row_min..=self.row_max {
            let xs = &mut self.rows[j];
            if xs.len() >= 2 {
                xs.sort_unstable_by(|a, b| a.total_cmp(b));
                for pair in xs.chunks_exact(2) {
                    let i0 = pair[0].ceil().max(0.0);
                    let i1 = (pair[1].ceil() - 1.0).min(w - 1.0);
                    if i0 <= i1 {
                        let (i0, i1) = (i0 as usize, i1 as usize);
                        span(j, i0, i1);
                        count += i1 - i0 + 1;
                    }
                }
            }
            xs.clear();
        }
        self.row_min = usize::MAX;
        self.row_max = 0;
        count
    }

    /// Fills one polygon given as rings (even-odd) into `mask: (H, W)`.
    pub fn fill_rings(&mut self, rings: &[&Ring], mask: &mut [u8]) -> usize {
        for r in rings {
            self.add_ring(r);
        }
        self.fill(mask)
    }

    /// Draws a segment of thickness `width_px` (a quad around the segment, extended by half the width at both
    /// ends so consecutive segments of a polyline join without gaps) into `mask: (H, W)`.
    pub fn draw_segment(&mut self, a: [f32; 2], b: [f32; 2], width_px: f32, mask: &mut [u8]) {
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len = (dx * dx + dy * dy).sqrt();
        let h = 0.5 * width_px.max(0.0);
        let (tx, ty) = if len > 1e-6 {
            (dx / len * h, dy / len * h)
        } else {
            (h, 0.0)
        };
        let (nx, ny) = (-ty, tx);
        let quad = [
            [a[0] - tx + nx, a[1] - ty + ny],
            [b[0] + tx + nx, b[1] + ty + ny],
            [b[0] + tx - nx, b[1] + ty - ny],
            [a[0] - tx - nx, a[1] - ty - ny],
        ];
        self.add_ring(&quad);
        self.fill(mask);
    }
}

/// Convex hull (Andrew's monotone chain) of `pts`, counter-clockwise in (u, v), without repeated end point.
/// Used to fill the silhouette of a convex solid (a box) as one polygon.
pub fn convex_hull(pts: &mut [[f32; 2]], out: &mut Vec<[f32; 2]>) {
    out.clear();
    if pts.len() < 3 {
        out.extend_from_slice(pts);
        return;
    }
    pts.sort_unstable_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    let cross = |o: [f32; 2], a: [f32; 2], b: [f32; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    for &p in pts.iter() {
        while out.len() >= 2 && cross(out[out.len() - 2], out[out.len() - 1], p) <= 0.0 {
            out.pop();
        }
        out.push(p);
    }
    let lower = out.len() + 1;
    for &p in pts.iter().rev().skip(1) {
        while out.len() >= lower && cross(out[out.len() - 2], out[out.len() - 1], p) <= 0.0 {
            out.pop();
        }
        out.push(p);
    }
    out.pop();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_aligned_rectangle_pixel_count() {
        // rectangle [2.3, 7.3) x [1.0, 4.0): columns 3..=7, rows 1..=3 -> 15 pixels
        let mut r = Rasterizer::new(10, 6);
        let mut m = vec![0u8; 60];
        let n = r.fill_rings(&[&[[2.3, 1.0], [7.3, 1.0], [7.3, 4.0], [2.3, 4.0]]], &mut m);
        assert_eq!(n, 15);
        assert_eq!(m.iter().filter(|&&v| v == 1).count(), 15);
        assert_eq!(m[10 + 3], 1);
        assert_eq!(m[10 + 2], 0);
        assert_eq!(m[4 * 10 + 3], 0);
    }

    #[test]
    fn hole_is_not_filled() {
        let mut r = Rasterizer::new(20, 20);
        let mut m = vec![0u8; 400];
        let outer = [[-0.5, -0.5], [19.5, -0.5], [19.5, 19.5], [-0.5, 19.5]];
        let hole = [[4.5, 4.5], [9.5, 4.5], [9.5, 9.5], [4.5, 9.5]];
        let n = r.fill_rings(&[&outer, &hole], &mut m);
        assert_eq!(n, 400 - 25);
        assert_eq!(m[7 * 20 + 7], 0);
    }

    #[test]
    fn hull_of_square_with_inner_points() {
        let mut pts = vec![
            [0.0, 0.0],
            [1.0, 0.0],
            [0.5, 0.5],
            [1.0, 1.0],
            [0.0, 1.0],
            [0.2, 0.7],
        ];
        let mut h = Vec::new();
        convex_hull(&mut pts, &mut h);
        assert_eq!(h.len(), 4);
    }
}
