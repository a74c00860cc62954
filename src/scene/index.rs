//! Spatial indices: a uniform grid of bounding boxes (map elements) and an indexed polygon set (drivable
//! area) answering point containment and point distance without scanning every edge.
use super::geometry::{point_segment_distance, Aabb};
use glam::DVec2;
use std::cell::RefCell;
use std::collections::HashMap;

/// Most cells one item is stored in; a larger (or non-finite) box goes to the list every query scans, so a
/// far-flung or huge item (a 1e5 m edge, a 1e308 coordinate) costs one entry, not a walk over its cells.
pub const MAX_ITEM_CELLS: u64 = 1 << 14;

/// Uniform grid over item bounding boxes. An item is stored in every cell its box touches (at most
/// [`MAX_ITEM_CELLS`]; larger items are kept in a list every query visits); queries deduplicate with a
/// per-query stamp, so a query costs the cells it touches plus their items, and never more than a scan of
/// every item (a query box larger than that scans the items instead of the cells). Callback order is
/// unspecified.
#[derive(Clone, Debug)]
pub struct GridIndex {
    cell: f64,
    cells: HashMap<(i32, i32), Vec<u32>>,
    /// Items too large (or not finite) to store per cell.
    large: Vec<u32>,
    boxes: Vec<Aabb>,
    stamp: RefCell<(u32, Vec<u32>)>,
}

impl GridIndex {
    pub fn new(cell: f64) -> Self {
        Self {
            cell,
            cells: HashMap::new(),
            large: Vec::new(),
            boxes: Vec::new(),
            stamp: RefCell::new((0, Vec::new())),
        }
    }
    #[inline]
    fn key(&self, v: f64) -> i32 {
        (v / self.cell).floor().clamp(-1e9, 1e9) as i32
    }
    /// Number of cells a box touches (saturating; non-finite boxes count as unbounded).
    fn cell_count(&self, b: &Aabb) -> u64 {
        let finite = b.min.is_finite() && b.max.is_finite();
        if !finite {
            return u64::MAX;
        }
        let nx = (self.key(b.max.x) as i64 - self.key(b.min.x) as i64 + 1).max(0) as u64;
        let ny = (self.key(b.max.y) as i64 - self.key(b.min.y) as i64 + 1).max(0) as u64;
        nx.saturating_mul(ny)
    }
    /// Inserts an item (ids are assigned densely in insertion order) and returns its id.
    pub fn insert(&mut self, b: Aabb) -> u32 {
        let id = self.boxes.len() as u32;
        self.boxes.push(b);
        if !b.is_empty() && self.cell_count(&b) > MAX_ITEM_CELLS {
            self.large.push(id);
        } else if !b.is_empty() {
            for ix in self.key(b.min.x)..=self.key(b.max.x) {
                for iy in self.key(b.min.y)..=self.key(b.max.y) {
                    self.cells.entry((ix, iy)).or_default().push(id);
                }
            }
        }
        id
    }
    pub fn len(&self) -> usize {
        self.boxes.len()
    }
    pub fn is_empty(&self) -> bool {
        self.boxes.is_empty()
    }
    /// Calls `f` once for each item whose box overlaps `q`.
    pub fn query(&self, q: &Aabb, mut f: impl FnMut(u32)) {
        let mut st = self.stamp.borrow_mut();
        st.0 = st.0.wrapping_add(1);
        if st.0 == 0 {
            st.1.iter_mut().for_each(|v| *v = 0);
            st.0 = 1;
        }
        let n = self.boxes.len();
        if st.1.len() < n {
            st.1.resize(n, 0);
        }
        let cur = st.0;
        let mut visit = |id: u32| {
            let i = id as usize;
            if st.1[i] != cur {
                st.1[i] = cur;
                if self.boxes[i].overlaps(q) {
                    f(id);
                }
            }
        };
        if self.cell_count(q) > (n as u64).saturating_mul(4).saturating_add(64) {
            // a query box larger than the index: scanning every item is cheaper than walking its cells
            (0..n as u32).for_each(visit);
            return;
        }
        self.large.iter().for_each(|&id| visit(id));
        for ix in self.key(q.min.x)..=self.key(q.max.x) {
            for iy in self.key(q.min.y)..=self.key(q.max.y) {
                if let Some(v) = self.cells.get(&(ix, iy)) {
                    v.iter().for_each(|&id| visit(id));
                }
            }
        }
    }
    /// Items whose box contains p.
    pub fn query_point(&self, p: DVec2, f: impl FnMut(u32)) {
        self.query(&Aabb { min: p, max: p }, f)
    }
}

/// Most horizontal bands of a [`PolygonSet`] (their height grows past 4 m for sets wider than 262 km).
pub const MAX_BANDS: usize = 1 << 16;

/// A set of polygons with holes (e.g. a GeoJSON MultiPolygon) with an edge index: containment counts ray
/// crossings among the edges of the point's horizontal band only; distance searches the edge grid.
#[derive(Clone, Debug, Default)]
pub struct PolygonSet {
    /// Every ring (outer rings and holes) as closed vertex lists; even-odd over all rings gives containment.
    pub rings: Vec<Vec<DVec2>>,
    /// (ring, vertex) per edge.
    edges: Vec<(DVec2, DVec2)>,
    band: f64,
    y0: f64,
    bands: Vec<Vec<u32>>,
    grid: Option<GridIndex>,
}

impl PolygonSet {
    /// Builds the set from rings (each ring implicitly closed).
    pub fn new(rings: Vec<Vec<DVec2>>) -> Self {
        let mut edges = Vec::new();
        let mut bb = Aabb::EMPTY;
        for r in &rings {
            let n = r.len();
            for i in 0..n {
                let (a, b) = (r[i], r[(i + 1) % n]);
                if a != b {
                    edges.push((a, b));
                    bb.add(a);
                }
            }
        }
        let band = 4.0;
        let mut s = Self {
            rings,
            edges,
            band,
            y0: 0.0,
            bands: Vec::new(),
            grid: None,
        };
        if s.edges.is_empty() {
            return s;
        }
        s.y0 = bb.min.y;
        // at most MAX_BANDS bands: a set spanning more than 4 * MAX_BANDS metres gets wider bands
        s.band = band.max((bb.max.y - bb.min.y) / MAX_BANDS as f64);
        let band = s.band;
        let nb = ((((bb.max.y - bb.min.y) / band).floor() as usize) + 1).min(MAX_BANDS);
        s.bands = vec![Vec::new(); nb];
        let mut grid = GridIndex::new(8.0);
        for (i, (a, b)) in s.edges.iter().enumerate() {
            let lo = ((a.y.min(b.y) - s.y0) / band).floor().max(0.0) as usize;
            let hi = (((a.y.max(b.y) - s.y0) / band).floor() as usize).min(nb - 1);
            for k in lo..=hi {
                s.bands[k].push(i as u32);
            }
            grid.insert(Aabb::from_points(&[*a, *b]));
        }
        s.grid = Some(grid);
        s
    }
    pub fn is_empty(&self) -> bool {
        self.edges.is_empty()
    }
    /// Even-odd containment over all rings.
    pub fn contains(&self, p: DVec2) -> bool {
        if self.edges.is_empty() {
            return false;
        }
        let k = ((p.y - self.y0) / self.band).floor();
        if k < 0.0 || k as usize >= self.bands.len() {
            return false;
        }
        let mut inside = false;
        for &e in &self.bands[k as usize] {
            let (a, b) = self.edges[e as usize];
            if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x {
                inside = !inside;
            }
        }
        inside
    }
    /// Distance from p to the nearest boundary edge, searching up to `max_dist` (returns INFINITY beyond).
    pub fn boundary_distance(&self, p: DVec2, max_dist: f64) -> f64 {
        let Some(grid) = &self.grid else {
            return f64::INFINITY;
        };
        let mut d = f64::INFINITY;
        let q = Aabb {
            min: p - DVec2::splat(max_dist),
            max: p + DVec2::splat(max_dist),
        };
        grid.query(&q, |i| {
            let (a, b) = self.edges[i as usize];
            d = d.min(point_segment_distance(p, a, b));
        });
        if d <= max_dist {
            d
        } else {
            f64::INFINITY
        }
    }
    /// Distance from p to the filled set (0 inside), searching up to `max_dist`.
    pub fn distance(&self, p: DVec2, max_dist: f64) -> f64 {
        if self.contains(p) {
            0.0
        } else {
            self.boundary_distance(p, max_dist)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_query_dedups_and_filters() {
        let mut g = GridIndex::new(1.0);
        let a = g.insert(Aabb {
            min: DVec2::new(0.0, 0.0),
            max: DVec2::new(3.0, 3.0),
        });
        let b = g.insert(Aabb {
            min: DVec2::new(5.0, 5.0),
            max: DVec2::new(6.0, 6.0),
        });
        let mut hits = vec![];
        g.query(
            &Aabb {
                min: DVec2::new(-1.0, -1.0),
                max: DVec2::new(10.0, 10.0),
            },
            |i| hits.push(i),
        );
        hits.sort();
        assert_eq!(hits, vec![a, b]);
        hits.clear();
        g.query_point(DVec2::new(2.5, 2.5), |i| hits.push(i));
        assert_eq!(hits, vec![a]);
    }

    #[test]
    fn polygon_set_with_hole() {
        let outer = vec![
            DVec2::new(0.0, 0.0),
            DVec2::new(20.0, 0.0),
            DVec2::new(20.0, 20.0),
            DVec2::new(0.0, 20.0),
        ];
        let hole = vec![
            DVec2::new(5.0, 5.0),
            DVec2::new(15.0, 5.0),
            DVec2::new(15.0, 15.0),
            DVec2::new(5.0, 15.0),
        ];
        let s = PolygonSet::new(vec![outer, hole]);
        assert!(s.contains(DVec2::new(2.0, 10.0)));
        assert!(!s.contains(DVec2::new(10.0, 10.0)));
        assert!(!s.contains(DVec2::new(25.0, 10.0)));
        assert!((s.distance(DVec2::new(10.0, 10.0), 50.0) - 5.0).abs() < 1e-12);
        assert!((s.distance(DVec2::new(23.0, 10.0), 50.0) - 3.0).abs() < 1e-12);
        assert_eq!(s.distance(DVec2::new(100.0, 10.0), 5.0), f64::INFINITY);
    }

    /// Far-away and huge items (a 1e5 m box at 1 m cells: 1e10 cells; a 1e308 coordinate) are stored in
    /// bounded time and still found; a query box larger than the index scans the items instead of its cells.
    #[test]
    fn grid_bounds_work_for_huge_and_far_boxes() {
        let t0 = std::time::Instant::now();
        let mut g = GridIndex::new(1.0);
        let small = g.insert(Aabb {
            min: DVec2::new(0.0, 0.0),
            max: DVec2::new(1.0, 1.0),
        });
        let huge = g.insert(Aabb {
            min: DVec2::new(-1e5, -1e5),
            max: DVec2::new(1e5, 1e5),
        });
        let far = g.insert(Aabb {
            min: DVec2::new(-1e308, 0.0),
            max: DVec2::new(1e308, 1.0),
        });
        let mut hits = vec![];
        g.query_point(DVec2::new(0.5, 0.5), |i| hits.push(i));
        hits.sort();
        assert_eq!(hits, vec![small, huge, far]);
        hits.clear();
        g.query_point(DVec2::new(5e4, -5e4), |i| hits.push(i));
        assert_eq!(hits, vec![huge]);
        hits.clear();
        let everything = Aabb {
            min: DVec2::splat(-1e300),
            max: DVec2::splat(1e300),
        };
        g.query(&everything, |i| hits.push(i));
        hits.sort();
        assert_eq!(hits, vec![small, huge, far]);
        assert!(t0.elapsed().as_secs_f64() < 2.0, "{:?}", t0.elapsed());
    }

    /// A drivable area with vertices at 1e5 m and 1e308 m builds and answers in bounded time (bands capped).
    #[test]
    fn polygon_set_far_vertices_are_bounded() {
        let t0 = std::time::Instant::now();
        for far in [1e5, 1e9, 1e308] {
            let ring = vec![
                DVec2::new(0.0, 0.0),
                DVec2::new(far, 0.0),
                DVec2::new(far, far),
                DVec2::new(0.0, far),
            ];
            let s = PolygonSet::new(vec![ring]);
            assert!(s.bands.len() <= MAX_BANDS);
            assert!(s.contains(DVec2::new(10.0, 10.0)), "far {far}");
            assert!(!s.contains(DVec2::new(-10.0, 10.0)), "far {far}");
            let d = s.distance(DVec2::new(-3.0, 10.0), 50.0);
            // at 1e308 squared lengths overflow (importers reject such coordinates); only boundedness counts
            assert!(far > 1e300 || (d - 3.0).abs() < 1e-9, "far {far}: {d}");
        }
        assert!(t0.elapsed().as_secs_f64() < 2.0, "{:?}", t0.elapsed());
    }
}
