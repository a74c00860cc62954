//! A spatial index over the recorded images of a log for reference retrieval ([`super::retrieval::retrieve`]
//! scans every frame per query).
//!
//! Per camera, the ground-plane positions of its images (the translation of each image's own `ego2global`) sit
//! in a 2-d tree (median splits on the wider axis, leaves of at most [`LEAF`] images, each node with its bounding
//! box). A query asks for the smallest `P_i = (c_i - c_ego) . v_ego > 0` (ahead) and the largest `P_i < 0`
//! (behind). Over a node's box `P` ranges between the values at its corners, so a branch-and-bound descent skips
//! every node that lies wholly on the wrong side or cannot beat the best image found so far. On a driven log
//! (images strung along a path) that visits O(log n) nodes; the worst case (many images at the same `P`) is a
//! scan. Results equal the linear scan's exactly, ties included (the earliest frame wins).
use std::collections::HashMap;

use glam::{DMat4, DVec2};

use super::retrieval::{heading_2d, Reference, References};
use crate::scene::camera::RecordedFrame;

/// Most images in a leaf.
pub const LEAF: usize = 8;
/// Slack (metres) on node bounds, so that rounding in the corner values never prunes a candidate.
const SLACK: f64 = 1e-6;

#[derive(Clone, Copy, Debug)]
struct Item {
    pos: DVec2,
    frame: usize,
    image: usize,
}

#[derive(Clone, Copy, Debug)]
struct Node {
    min: DVec2,
    max: DVec2,
    /// Items `lo..hi` of the tree's item list.
    lo: usize,
    hi: usize,
    /// Child nodes (leaves have none).
    kids: Option<(usize, usize)>,
}

/// The 2-d tree of one camera's images.
#[derive(Clone, Debug, Default)]
struct Tree {
    items: Vec<Item>,
    nodes: Vec<Node>,
}

impl Tree {
    fn build(mut items: Vec<Item>) -> Tree {
        let mut t = Tree {
            items: vec![],
            nodes: vec![],
        };
        if !items.is_empty() {
            let n = items.len();
            t.split(&mut items, 0, n);
        }
        t.items = items;
        t
    }

    fn split(&mut self, items: &mut [Item], lo: usize, hi: usize) -> usize {
        let (mut min, mut max) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for it in &items[lo..hi] {
            min = min.min(it.pos);
            max = max.max(it.pos);
        }
        let id = self.nodes.len();
        self.nodes.push(Node {
            min,
            max,
            lo,
            hi,
            kids: None,
        });
        if hi - lo > LEAF {
            let axis = usize::from(max.y - min.y > max.x - min.x);
            let mid = (lo + hi) / 2;
            items[lo..hi]
                .select_nth_unstable_by(mid - lo, |a, b| a.pos[axis].total_cmp(&b.pos[axis]));
            let l = self.split(items, lo, mid);
            let r = self.split(items, mid, hi);
            self.nodes[id].kids = Some((l, r));
        }
        id
    }

    /// Range of `(c - o) . v` over a node's box.
    fn bounds(n: &Node, o: DVec2, v: DVec2) -> (f64, f64) {
        let pick = |lo_side: bool, a: f64, b: f64| if lo_side { a } else { b };
        let low = DVec2::new(
            pick(v.x >= 0.0, n.min.x, n.max.x),
            pick(v.y >= 0.0, n.min.y, n.max.y),
        );
        let high = DVec2::new(
            pick(v.x >= 0.0, n.max.x, n.min.x),
            pick(v.y >= 0.0, n.max.y, n.min.y),
        );
        ((low - o).dot(v) - SLACK, (high - o).dot(v) + SLACK)
    }

    /// Best `(frame, image, P)` on one side: `ahead` = smallest P > 0, else largest P < 0; ties to the
    /// earliest frame. `visited` counts nodes.
    fn best(
        &self,
        o: DVec2,
        v: DVec2,
        ahead: bool,
        visited: &mut usize,
    ) -> Option<(usize, usize, f64)> {
        let mut best: Option<(usize, usize, f64)> = None;
        if self.nodes.is_empty() {
            return None;
        }
        let better = |c: (usize, usize, f64), b: Option<(usize, usize, f64)>| match b {
            None => true,
            Some(b) => {
                if ahead {
                    c.2 < b.2 || (c.2 == b.2 && c.0 < b.0)
                } else {
                    c.2 > b.2 || (c.2 == b.2 && c.0 < b.0)
                }
            }
        };
        let mut stack = vec![0usize];
        while let Some(id) = stack.pop() {
            *visited += 1;
            let n = self.nodes[id];
            let (lo, hi) = Self::bounds(&n, o, v);
            // Wholly on the wrong side, or cannot beat the best (a tie may still win on the frame).
            let skip = if ahead {
                hi <= 0.0 || best.is_some_and(|b| lo > b.2)
            } else {
                lo >= 0.0 || best.is_some_and(|b| hi < b.2)
            };
            if skip {
                continue;
            }
            match n.kids {
                None => {
                    for it in &self.items[n.lo..n.hi] {
                        let p = (it.pos - o).dot(v);
                        let c = (it.frame, it.image, p);
                        if ((ahead && p > 0.0) || (!ahead && p < 0.0)) && better(c, best) {
                            best = Some(c);
                        }
                    }
                }
                Some((l, r)) => {
                    // Visit the child nearer to P = 0 first (pushed last).
                    let (ll, lh) = Self::bounds(&self.nodes[l], o, v);
                    let (rl, rh) = Self::bounds(&self.nodes[r], o, v);
                    let key = |lo: f64, hi: f64| if ahead { lo.max(0.0) } else { -hi.min(0.0) };
                    if key(ll, lh) <= key(rl, rh) {
                        stack.push(r);
                        stack.push(l);
                    } else {
                        stack.push(l);
                        stack.push(r);
                    }
                }
            }
        }
        best
    }
}

/// The index of every camera's recorded images of one log.
#[derive(Clone, Debug, Default)]
pub struct FrameIndex {
    trees: HashMap<String, Tree>,
}

impl FrameIndex {
    /// Indexes `frames` (the first image of each camera per frame, as [`super::retrieval::retrieve`] takes).
    pub fn new(frames: &[RecordedFrame]) -> FrameIndex {
        let mut per: HashMap<String, Vec<Item>> = HashMap::new();
        for (f, fr) in frames.iter().enumerate() {
            for (i, img) in fr.images.iter().enumerate() {
                let first = fr.images.iter().position(|x| x.camera == img.camera) == Some(i);
                if first {
                    per.entry(img.camera.clone()).or_default().push(Item {
                        pos: img.ego2global.w_axis.truncate().truncate(),
                        frame: f,
                        image: i,
                    });
                }
            }
        }
        FrameIndex {
            trees: per.into_iter().map(|(k, v)| (k, Tree::build(v))).collect(),
        }
    }

    /// Nearest image of `camera` ahead of / behind the pose: `(frame, image, P)`, and the nodes visited.
    pub fn nearest(
        &self,
        camera: &str,
        ego2global: &DMat4,
        ahead: bool,
    ) -> (Option<(usize, usize, f64)>, usize) {
        let mut visited = 0;
        let (Some(t), Some(v)) = (self.trees.get(camera), heading_2d(ego2global)) else {
            return (None, 0);
        };
        let o = ego2global.w_axis.truncate().truncate();
        (t.best(o, v, ahead, &mut visited), visited)
    }

    /// The same references as [`super::retrieval::retrieve`] on the frames this index was built from.
    pub fn retrieve(
        &self,
        frames: &[RecordedFrame],
        camera: &str,
        ego2global: &DMat4,
    ) -> References {
        let inv = ego2global.inverse();
        let mk = |c: Option<(usize, usize, f64)>| {
            c.map(|(f, i, along)| Reference {
                frame: f,
                image: i,
                along,
                ref2cur: inv * frames[f].images[i].ego2global,
            })
        };
        References {
            front: mk(self.nearest(camera, ego2global, true).0),
            rear: mk(self.nearest(camera, ego2global, false).0),
        }
    }
}
