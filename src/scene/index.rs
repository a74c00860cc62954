//! Spatial indices: a uniform grid of bounding boxes (map elements) and an indexed polygon set (drivable
//! area) answering point containment and point distance without scanning every edge.
use super::geometry::{point_segment_distance, Aabb};
use glam::DVec2;
use std::cell::RefCell;
use std::collections::HashMap;

/// Uniform grid over item bounding boxes. An item is stored in every cell its box touches; queries
/// deduplicate with a per-query stamp, so a query costs the cells it touches plus their items.
#[derive(Clone, Debug)]
pub struct GridIndex {
    cell: f64,
    cells: HashMap<(i32, i32), Vec<u32>>,
    boxes: Vec<Aabb>,
    stamp: RefCell<(u32, Vec<u32>)>,
}

impl GridIndex {
    pub fn new(cell: f64) -> Self {
        Self {
            cell,
            cells: HashMap::new(),
            boxes: Vec::new(),
            stamp: RefCell::new((0, Vec::new())),
        }
    }
    #[inline]
    fn key(&self, v: f64) -> i32 {
        (v / self.cell).floor().clamp(-1e9, 1e9) as i32
    }
    /// Inserts an item (ids are assigned densely in insertion order) and returns its id.
    pub fn insert(&mut self, b: Aabb) -> u32 {
        let id = self.boxes.len() as u32;
        self.boxes.push(b);
        if !b.is_empty() {
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
        for ix in self.key(q.min.x)..=self.key(q.max.x) {
            for iy in self.key(q.min.y)..=self.key(q.max.y) {
                if let Some(v) = self.cells.get(&(ix, iy)) {
                    for &id in v {
                        let i = id as usize;
                        if st.1[i] != cur {
                            st.1[i] = cur;
                            if self.boxes[i].overlaps(q) {
                                f(id);
                            }
                        }
                    }
                }
            }
        }
    }
    /// Items whose box contains p.
    pub fn query_point(&self, p: DVec2, f: impl FnMut(u32)) {
        self.query(&Aabb { min: p, max: p }, f)
    }
}

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
        let nb = (((bb.max.y - bb.min.y) / band).floor() as usize) + 1;
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
}
