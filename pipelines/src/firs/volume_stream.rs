//! Volume mode streamed: the sweep's frames go in one at a time (or a few at a time, for the
//! threads), occupancy slices come out, and the world volume's z-slices come out of those, so
//! nothing holds the whole stack. Same steps, same numbers as the whole-array functions of
//! [`crate::firs::volume`] ([`segment_slices`](crate::firs::volume::segment_slices),
//! [`resample`](crate::firs::volume::resample)); where a step needs more than one slice it
//! holds a bounded slab:
//!
//! | step | what it holds |
//! |---|---|
//! | ratio to the reference, shadow correction along the laser rows (2-D) | the slice |
//! | fill of the blocked streaks (3-D diffusion, [`fill_blocked`]) | the slices of the open streaks, at most [`SegmentStream::max_fill_slab`] plus one either side |
//! | segmentation, vertical opening (2-D) | the slice |
//! | 6-connected small-region removal (3-D) | the occupancy slices whose components are still undecided (fewer than `min_region` voxels and still growing): at most `min_region` slices, in practice one to three |
//! | resampling to world voxels (trilinear) | the slices a world z-slice reads: for sheets parallel to the grid's `xy` planes, four |
//!
//! **Blocked streaks.** [`fill_blocked`] diffuses over each 6-connected blocked component with
//! its unblocked neighbours fixed, so components are independent and each one, taken whole
//! with a slice of context either side, gives exactly the whole-array numbers. A component
//! deeper than `max_fill_slab` slices (a bubble, not dust) is cut there: the part held is
//! filled as if the stack ended at its last slice, and the rest takes the filled slice as its
//! context. [`StreamStats::forced_fills`] counts such cuts; with none, the streamed occupancy
//! equals [`segment_slices`](crate::firs::volume::segment_slices)' bit for bit.
//!
//! **Small regions.** Each slice's mask is labelled in 2-D (4-connected) and its components
//! are joined to the previous slice's where they overlap (a union-find over the components).
//! A component is decided as soon as it reaches `min_region` voxels (kept: components only
//! grow) or has no voxel in the newest slice (closed: removed if under `min_region`); a slice
//! goes out once all its components are decided.

use std::collections::VecDeque;

use rayon::prelude::*;

use crate::firs::mesh::Grid;
use crate::firs::volume::{
    check_len, correct_shadows, fill_blocked, pixels, ratio_to_reference, remove_thin_horizontal,
    resample_planes, segment, SliceMap, VolumeError, VolumeParams,
};
use crate::vec3::{dot, sub, V3};

/// What the streamed steps held at most, in slices of the stack.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// Frames taken.
    pub pushed: usize,
    /// The blocked-fill slab: open streaks' slices, their context and the newest slice.
    pub max_fill_slices: usize,
    /// Occupancy slices waiting for the small-region decision.
    pub max_clean_slices: usize,
    /// Blocked components cut at `max_fill_slab` (filled approximately there).
    pub forced_fills: usize,
}

/// Steps 1–5 of volume mode streamed: [`push`](Self::push) the sweep's frames in order
/// (first to last, or last to first with `reverse`), take the occupancy slices with
/// [`pop`](Self::pop) as they come (each with its index in the sweep), [`finish`](Self::finish)
/// at the end.
pub struct SegmentStream {
    width: usize,
    height: usize,
    count: usize,
    reverse: bool,
    reference: Vec<f32>,
    params: VolumeParams,
    max_fill_slab: usize,
    pushed: usize,
    emitted: usize,
    /// The last slice out of the fill stage (its final ratio), context for the next streak.
    ctx: Option<Vec<f32>>,
    /// Corrected ratio and blocked mask of the slices with open streaks, in arrival order.
    pending: VecDeque<(Vec<f32>, Vec<u8>)>,
    clean: Clean,
    ready: VecDeque<(usize, Vec<f32>)>,
    stats: StreamStats,
}

impl SegmentStream {
    /// The default bound on a blocked streak's depth, slices.
    pub const DEFAULT_FILL_SLAB: usize = 8;

    /// A stream for a sweep of `count` frames of `width × height` against `reference` (see
    /// [`median_reference`](crate::firs::volume::median_reference)). `reverse`: the frames
    /// come last to first.
    pub fn new(
        reference: Vec<f32>,
        width: usize,
        height: usize,
        count: usize,
        reverse: bool,
        params: &VolumeParams,
    ) -> Result<Self, VolumeError> {
        let n = pixels(width, height)?;
        check_len(n, reference.len())?;
        if count == 0 {
            return Err(VolumeError::NoSlices);
        }
        if !(params.threshold > params.dark && params.threshold <= 1.0) {
            return Err(VolumeError::BadParameter("threshold must lie in (dark, 1]"));
        }
        if !(params.dark > 0.0 && params.dark < 1.0) {
            return Err(VolumeError::BadParameter("dark must lie in (0, 1)"));
        }
        Ok(SegmentStream {
            width,
            height,
            count,
            reverse,
            reference,
            params: *params,
            max_fill_slab: Self::DEFAULT_FILL_SLAB,
            pushed: 0,
            emitted: 0,
            ctx: None,
            pending: VecDeque::new(),
            clean: Clean::new(width, height, params.min_region),
            ready: VecDeque::new(),
            stats: StreamStats::default(),
        })
    }

    /// Bounds a blocked streak's depth to `slices` (at least 1); deeper ones are cut (see the
    /// module).
    pub fn max_fill_slab(mut self, slices: usize) -> Self {
        self.max_fill_slab = slices.max(1);
        self
    }

    /// What the stream held so far.
    pub fn stats(&self) -> StreamStats {
        self.stats
    }

    /// Takes the next frame of the sweep.
    pub fn push(&mut self, frame: &[f32]) -> Result<(), VolumeError> {
        self.push_many(&[frame])
    }

    /// Takes the next frames of the sweep; their 2-D steps run in parallel.
    pub fn push_many(&mut self, frames: &[&[f32]]) -> Result<(), VolumeError> {
        if self.pushed + frames.len() > self.count {
            return Err(VolumeError::BadParameter("more frames than the sweep's count"));
        }
        let (w, h, p) = (self.width, self.height, self.params);
        let reference = &self.reference;
        let corrected: Vec<Result<Corrected, VolumeError>> = frames
            .par_iter()
            .map(|f| {
                check_len(w * h, f.len())?;
                let mut q = ratio_to_reference(f, reference)?;
                let blocked = correct_shadows(&mut q, w, h, p.laser, p.dark, p.fill_iterations)?;
                Ok((q, blocked))
            })
            .collect();
        for c in corrected {
            let (q, b) = c?;
            self.take_corrected(q, b)?;
        }
        Ok(())
    }

    /// The next occupancy slice, `(index in the sweep, width × height values)`, in the order
    /// the frames came.
    pub fn pop(&mut self) -> Option<(usize, Vec<f32>)> {
        self.ready.pop_front()
    }

    /// After the last frame: releases what is held. Refuses a sweep short of its count.
    pub fn finish(&mut self) -> Result<(), VolumeError> {
        if self.pushed != self.count {
            return Err(VolumeError::Length { expected: self.count, got: self.pushed });
        }
        if !self.pending.is_empty() {
            self.fill_pending(None)?;
        }
        self.clean.release(&mut self.ready, true);
        Ok(())
    }

    fn index(&self, arrival: usize) -> usize {
        if self.reverse {
            self.count - 1 - arrival
        } else {
            arrival
        }
    }

    fn take_corrected(&mut self, q: Vec<f32>, b: Vec<u8>) -> Result<(), VolumeError> {
        self.pushed += 1;
        self.stats.pushed = self.pushed;
        let any = b.iter().any(|&x| x != 0);
        if let Some((_, last)) = self.pending.back() {
            let joined = last.iter().zip(&b).any(|(&x, &y)| x != 0 && y != 0);
            let held = self.pending.len() + usize::from(self.ctx.is_some()) + 1;
            self.stats.max_fill_slices = self.stats.max_fill_slices.max(held);
            if !joined {
                // The open streaks end here: exact, with this slice as their far context.
                self.fill_pending(Some(&q))?;
            } else if self.pending.len() >= self.max_fill_slab {
                self.stats.forced_fills += 1;
                self.fill_pending(None)?;
            }
        }
        if self.pending.is_empty() && !any {
            self.emit(q)?;
        } else {
            self.pending.push_back((q, b));
        }
        let held = self.pending.len() + usize::from(self.ctx.is_some());
        self.stats.max_fill_slices = self.stats.max_fill_slices.max(held);
        Ok(())
    }

    /// Fills the pending slices' blocked voxels on the slab `ctx, pending…, lookahead` laid
    /// out in the sweep's order, then sends them on.
    fn fill_pending(&mut self, lookahead: Option<&[f32]>) -> Result<(), VolumeError> {
        let n = self.width * self.height;
        let zeros = vec![0u8; n];
        let mut parts: Vec<(&[f32], &[u8])> = Vec::new();
        if let Some(c) = &self.ctx {
            parts.push((c, &zeros));
        }
        for (q, b) in &self.pending {
            parts.push((q, b));
        }
        if let Some(l) = lookahead {
            parts.push((l, &zeros));
        }
        if self.reverse {
            parts.reverse();
        }
        let mut q: Vec<f32> = parts.iter().flat_map(|p| p.0.iter().copied()).collect();
        let b: Vec<u8> = parts.iter().flat_map(|p| p.1.iter().copied()).collect();
        let depth = parts.len();
        drop(parts);
        fill_blocked(&mut q, &b, [self.width, self.height, depth], self.params.fill_iterations)?;
        // Back to arrival order: the pending slices sit after the context (before it when
        // reversed).
        let has_ctx = usize::from(self.ctx.is_some());
        let k = self.pending.len();
        let pending: Vec<(Vec<f32>, Vec<u8>)> = self.pending.drain(..).collect();
        for (i, (mut slice, _)) in pending.into_iter().enumerate() {
            let at = if self.reverse { depth - 1 - has_ctx - i } else { has_ctx + i };
            slice.copy_from_slice(&q[at * n..(at + 1) * n]);
            self.emit(slice)?;
        }
        debug_assert!(k > 0);
        Ok(())
    }

    /// Steps 3–4 on a finished ratio slice, then the small-region stage.
    fn emit(&mut self, q: Vec<f32>) -> Result<(), VolumeError> {
        let (w, h, p) = (self.width, self.height, self.params);
        let raw = segment(&q, 0.5 * p.threshold);
        let mut mask = raw.clone();
        remove_thin_horizontal(&mut mask, &segment(&q, p.threshold), w, h, p.min_height)?;
        let mut occ: Vec<f32> = q.iter().map(|&x| 1.0 - x.clamp(0.0, 1.0)).collect();
        for ((o, &r), &m) in occ.iter_mut().zip(&raw).zip(&mask) {
            if r == 1 && m == 0 {
                *o = 0.0;
            }
        }
        let idx = self.index(self.emitted);
        self.emitted += 1;
        self.clean.push(idx, occ, &mask, &mut self.ready);
        self.stats.max_clean_slices = self.stats.max_clean_slices.max(self.clean.max_held);
        self.ctx = Some(q);
        Ok(())
    }
}

/// A slice's corrected ratio and blocked mask.
type Corrected = (Vec<f32>, Vec<u8>);

const NONE: u32 = u32::MAX;

#[derive(Debug, Clone, Copy)]
struct Node {
    parent: u32,
    count: usize,
    /// Arrival number of the newest slice it has voxels in.
    last: usize,
}

struct Held {
    idx: usize,
    occ: Vec<f32>,
    labels: Vec<u32>,
    nodes: Vec<u32>,
}

/// The streamed 6-connected small-region removal.
struct Clean {
    width: usize,
    height: usize,
    min_region: usize,
    nodes: Vec<Node>,
    held: VecDeque<Held>,
    /// Labels of the newest slice (its components' nodes).
    prev: Vec<u32>,
    arrivals: usize,
    max_held: usize,
}

impl Clean {
    fn new(width: usize, height: usize, min_region: usize) -> Self {
        Clean {
            width,
            height,
            min_region,
            nodes: Vec::new(),
            held: VecDeque::new(),
            prev: vec![NONE; width * height],
            arrivals: 0,
            max_held: 0,
        }
    }

    fn find(&mut self, mut x: u32) -> u32 {
        while self.nodes[x as usize].parent != x {
            let p = self.nodes[x as usize].parent;
            self.nodes[x as usize].parent = self.nodes[p as usize].parent;
            x = p;
        }
        x
    }

    fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let nb = self.nodes[rb as usize];
            let na = &mut self.nodes[ra as usize];
            na.count = na.count.saturating_add(nb.count);
            na.last = na.last.max(nb.last);
            self.nodes[rb as usize].parent = ra;
        }
    }

    fn push(&mut self, idx: usize, occ: Vec<f32>, mask: &[u8], out: &mut VecDeque<(usize, Vec<f32>)>) {
        let (w, h) = (self.width, self.height);
        let s = self.arrivals;
        self.arrivals += 1;
        let mut labels = vec![NONE; w * h];
        let mut here = Vec::new();
        let mut stack = Vec::new();
        for seed in 0..w * h {
            if mask[seed] == 0 || labels[seed] != NONE {
                continue;
            }
            let id = self.nodes.len() as u32;
            labels[seed] = id;
            stack.push(seed);
            let mut count = 0;
            while let Some(p) = stack.pop() {
                count += 1;
                let (u, v) = (p % w, p / w);
                let nbs = [
                    (u > 0).then(|| p - 1),
                    (u + 1 < w).then(|| p + 1),
                    (v > 0).then(|| p - w),
                    (v + 1 < h).then(|| p + w),
                ];
                for q in nbs.into_iter().flatten() {
                    if mask[q] != 0 && labels[q] == NONE {
                        labels[q] = id;
                        stack.push(q);
                    }
                }
            }
            self.nodes.push(Node { parent: id, count, last: s });
            here.push(id);
        }
        for (&l, p) in labels.iter().zip(0..) {
            let q: u32 = self.prev[p];
            if l != NONE && q != NONE {
                self.union(l, q);
            }
        }
        self.prev.copy_from_slice(&labels);
        self.held.push_back(Held { idx, occ, labels, nodes: here });
        self.max_held = self.max_held.max(self.held.len());
        self.release(out, false);
        self.compact();
    }

    /// `Some(kept)` once the node's component is decided.
    fn decided(&mut self, node: u32, finished: bool) -> Option<bool> {
        let r = self.find(node) as usize;
        let newest = self.arrivals.saturating_sub(1);
        if self.nodes[r].count >= self.min_region {
            Some(true)
        } else if finished || self.nodes[r].last < newest {
            Some(false)
        } else {
            None
        }
    }

    fn release(&mut self, out: &mut VecDeque<(usize, Vec<f32>)>, finished: bool) {
        while let Some(front) = self.held.front() {
            let nodes = front.nodes.clone();
            let mut fate = Vec::with_capacity(nodes.len());
            for &n in &nodes {
                match self.decided(n, finished) {
                    Some(k) => fate.push((n, k)),
                    None => return,
                }
            }
            let Some(mut slice) = self.held.pop_front() else { return };
            if fate.iter().any(|&(_, k)| !k) {
                for (o, &l) in slice.occ.iter_mut().zip(&slice.labels) {
                    if l != NONE && fate.iter().any(|&(n, k)| n == l && !k) {
                        *o = 0.0;
                    }
                }
            }
            out.push_back((slice.idx, slice.occ));
        }
    }

    /// Renumbers the union-find to the components the held slices and the newest slice refer
    /// to, once the dead nodes dominate.
    fn compact(&mut self) {
        let live = self.held.iter().map(|h| h.nodes.len()).sum::<usize>() + self.width * self.height;
        if self.nodes.len() <= 4 * live + 4096 {
            return;
        }
        let mut map = vec![NONE; self.nodes.len()];
        let mut fresh: Vec<Node> = Vec::new();
        let mut renumber = |this: &mut Clean, l: u32| -> u32 {
            let r = this.find(l) as usize;
            if map[r] == NONE {
                map[r] = fresh.len() as u32;
                let n = this.nodes[r];
                fresh.push(Node { parent: map[r], count: n.count, last: n.last });
            }
            map[r]
        };
        let mut held = std::mem::take(&mut self.held);
        for hslice in held.iter_mut() {
            for l in hslice.labels.iter_mut().filter(|l| **l != NONE) {
                *l = renumber(self, *l);
            }
            let mut nodes: Vec<u32> = hslice.nodes.iter().map(|&n| renumber(self, n)).collect();
            nodes.sort_unstable();
            nodes.dedup();
            hslice.nodes = nodes;
        }
        let mut prev = std::mem::take(&mut self.prev);
        for l in prev.iter_mut().filter(|l| **l != NONE) {
            *l = renumber(self, *l);
        }
        self.held = held;
        self.prev = prev;
        self.nodes = fresh;
    }
}

/// Whether the world grid's z-slices, in order, read the stack's slices last to first (then
/// feed [`ResampleStream`] and [`SegmentStream`] the sweep reversed).
pub fn slices_reversed(map: &SliceMap, grid: &Grid) -> Result<bool, VolumeError> {
    let inv = map.inverse()?;
    Ok(inv[2][2] * grid.voxel[2] < 0.0)
}

/// Step 6 streamed: takes occupancy slices in the sweep's order (or its reverse, see
/// [`slices_reversed`]) and gives the world grid's z-slices in order, each as soon as the
/// slices it reads are in, holding only those.
pub struct ResampleStream {
    origin: V3,
    inv: [V3; 3],
    grid: Grid,
    dims: [usize; 3],
    reverse: bool,
    /// `(index, slice)` in arrival order.
    window: VecDeque<(usize, Vec<f32>)>,
    arrived: usize,
    next_k: usize,
    max_window: usize,
}

impl ResampleStream {
    /// A stream from a stack of `count` slices of `width × height` at `map` to `grid`.
    pub fn new(
        map: &SliceMap,
        grid: &Grid,
        width: usize,
        height: usize,
        count: usize,
    ) -> Result<Self, VolumeError> {
        let inv = map.inverse()?;
        pixels(width, height)?;
        if count == 0 {
            return Err(VolumeError::NoSlices);
        }
        let [nx, ny, nz] = grid.dims;
        if nx == 0 || ny == 0 || nz == 0 {
            return Err(VolumeError::BadSize { width: nx, height: ny });
        }
        Ok(ResampleStream {
            origin: map.origin,
            inv,
            grid: *grid,
            dims: [width, height, count],
            reverse: slices_reversed(map, grid)?,
            window: VecDeque::new(),
            arrived: 0,
            next_k: 0,
            max_window: 0,
        })
    }

    /// Whether it wants the slices last to first.
    pub fn reversed(&self) -> bool {
        self.reverse
    }

    /// The most slices it has held at once.
    pub fn max_window(&self) -> usize {
        self.max_window
    }

    /// The stack slices z-slice `k` may read, `[lo, hi]` unclamped (one slice of margin each
    /// way): the slice coordinate is affine in the grid, so its extremes are at the corners.
    fn span(&self, k: usize) -> (i64, i64) {
        let [nx, ny, _] = self.grid.dims;
        let g = &self.grid;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for (i, j) in [(0, 0), (nx - 1, 0), (0, ny - 1), (nx - 1, ny - 1)] {
            let p = [
                g.origin[0] + i as f64 * g.voxel[0],
                g.origin[1] + j as f64 * g.voxel[1],
                g.origin[2] + k as f64 * g.voxel[2],
            ];
            let s = dot(self.inv[2], sub(p, self.origin));
            lo = lo.min(s);
            hi = hi.max(s);
        }
        (lo.floor() as i64 - 1, hi.floor() as i64 + 2)
    }

    /// Takes the next occupancy slice, `index` its place in the sweep.
    pub fn push(&mut self, index: usize, slice: Vec<f32>) -> Result<(), VolumeError> {
        let [w, h, c] = self.dims;
        check_len(w * h, slice.len())?;
        let expected = if self.reverse { c.checked_sub(1 + self.arrived) } else { Some(self.arrived) };
        if expected != Some(index) {
            return Err(VolumeError::BadParameter("slices out of the sweep's order for the resampling"));
        }
        self.arrived += 1;
        // Only the slices a z-slice from the next one on reads are kept.
        let nz = self.grid.dims[2];
        let i = index as i64;
        let wanted = self.next_k < nz && {
            let (a, b) = (self.span(self.next_k), self.span(nz - 1));
            let (lo, hi) = (a.0.min(b.0), a.1.max(b.1));
            if self.reverse {
                i <= a.1.max(a.0) && i >= lo
            } else {
                i >= a.0.min(a.1) && i <= hi
            }
        };
        if wanted {
            self.window.push_back((index, slice));
            self.max_window = self.max_window.max(self.window.len());
        }
        Ok(())
    }

    /// Fills `out` with the next z-slice if the slices it reads are in (all of them once
    /// `finished`); returns its index, or `None` when it must wait or all are out.
    pub fn next(&mut self, out: &mut [f32], finished: bool) -> Result<Option<usize>, VolumeError> {
        let [nx, ny, nz] = self.grid.dims;
        check_len(nx * ny, out.len())?;
        if self.next_k >= nz {
            return Ok(None);
        }
        let c = self.dims[2] as i64;
        let k = self.next_k;
        let (lo, hi) = self.span(k);
        let (lo_c, hi_c) = (lo.max(0), hi.min(c - 1));
        if lo_c <= hi_c && !finished {
            let have = self.arrived as i64;
            let ready = if self.reverse { lo_c >= c - have } else { hi_c < have };
            if !ready {
                return Ok(None);
            }
        }
        // Slices no later z-slice reads go: the span moves one way along the sweep.
        let (nlo, nhi) = if k + 1 < nz { self.span(k + 1) } else { (i64::MAX, i64::MIN) };
        let drop_below = lo.min(nlo);
        let drop_above = hi.max(nhi);
        while let Some(&(i, _)) = self.window.front() {
            let i = i as i64;
            if (!self.reverse && i < drop_below) || (self.reverse && i > drop_above) {
                self.window.pop_front();
            } else {
                break;
            }
        }
        // The held slices in the sweep's order, from `first`.
        let mut planes: Vec<(usize, &[f32])> = self.window.iter().map(|(i, s)| (*i, s.as_slice())).collect();
        planes.sort_unstable_by_key(|p| p.0);
        let first = planes.first().map_or(0, |p| p.0);
        let contiguous = planes.iter().enumerate().all(|(n, p)| p.0 == first + n);
        let planes: Vec<&[f32]> = planes.into_iter().map(|p| p.1).collect();
        if !contiguous
            || !resample_planes(&planes, first, self.dims, self.origin, &self.inv, &self.grid, k, out)
        {
            return Err(VolumeError::BadParameter(
                "resampling: a stack slice was not pushed (push every slice of the sweep before finishing)",
            ));
        }
        self.next_k += 1;
        Ok(Some(k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::firs::volume::{segment_slices, Laser};

    /// Runs the stream over `frames` and returns the occupancy slices in the sweep's order.
    fn streamed(
        frames: &[Vec<f32>],
        reference: &[f32],
        w: usize,
        h: usize,
        p: &VolumeParams,
        reverse: bool,
        slab: usize,
    ) -> (Vec<f32>, StreamStats) {
        let n = frames.len();
        let mut s = SegmentStream::new(reference.to_vec(), w, h, n, reverse, p).unwrap().max_fill_slab(slab);
        let mut out = vec![Vec::new(); n];
        let order: Vec<usize> = if reverse { (0..n).rev().collect() } else { (0..n).collect() };
        for &i in &order {
            s.push(&frames[i]).unwrap();
            while let Some((k, o)) = s.pop() {
                out[k] = o;
            }
        }
        s.finish().unwrap();
        while let Some((k, o)) = s.pop() {
            out[k] = o;
        }
        assert!(out.iter().all(|o| o.len() == w * h));
        (out.concat(), s.stats())
    }

    #[test]
    fn streamed_segmentation_equals_the_whole_stack() {
        // Rows of object and shadowed liquid, dust streaks to the far wall one, two and four
        // slices deep (blocked components), specks of 1–5 voxels over one to three slices,
        // a thin horizontal streak.
        let (w, h, n) = (40, 24, 30);
        let mut frames = vec![vec![1.0f32; w * h]; n];
        let mut set = |s: usize, u: std::ops::Range<usize>, v: std::ops::Range<usize>, x: f32| {
            for vv in v {
                for uu in u.clone() {
                    frames[s][vv * w + uu] = x;
                }
            }
        };
        for s in 5..25 {
            let r = 3 + (s as i64 - 15).unsigned_abs() as usize / 3;
            set(s, 10..30 - r, r..20 - r / 2, 0.02);
            set(s, 30 - r..w, r..20 - r / 2, 0.4);
        }
        for (s0, depth, v) in [(2, 1, 21), (8, 2, 21), (12, 4, 1), (20, 4, 22)] {
            for s in s0..s0 + depth {
                set(s, 6..w, v..v + 2, 0.03);
            }
        }
        for (s0, depth, u, v, size) in [(1, 1, 3, 3, 1), (3, 3, 35, 1, 1), (27, 2, 5, 5, 2)] {
            for s in s0..s0 + depth {
                set(s, u..u + size, v..v + size + 3, 0.01);
            }
        }
        set(17, 2..8, 22..23, 0.01);
        let reference = vec![2.0f32; w * h];
        let scaled: Vec<Vec<f32>> = frames.iter().map(|f| f.iter().map(|x| x * 2.0).collect()).collect();
        let refs: Vec<&[f32]> = scaled.iter().map(Vec::as_slice).collect();
        let p =
            VolumeParams { min_height: 3, min_region: 20, laser: Laser::PlusU, ..VolumeParams::default() };
        let whole = segment_slices(&refs, &reference, w, h, &p).unwrap();
        for reverse in [false, true] {
            let (data, stats) = streamed(&scaled, &reference, w, h, &p, reverse, 8);
            assert_eq!(stats.forced_fills, 0);
            assert_eq!(data, whole.data, "reverse {reverse}");
            assert!(stats.max_fill_slices <= 6, "{stats:?}");
            assert!(stats.max_clean_slices <= 4, "{stats:?}");
        }
        // Cut at two slices: the four-slice streaks are filled in pieces (counted), the rest
        // is unchanged.
        let (data, stats) = streamed(&scaled, &reference, w, h, &p, false, 2);
        assert_eq!(stats.forced_fills, 2, "{stats:?}");
        let differs: Vec<usize> =
            (0..data.len()).filter(|&i| data[i] != whole.data[i]).map(|i| i / (w * h)).collect();
        assert!(
            !differs.is_empty() && differs.iter().all(|s| (12..16).contains(s) || (20..24).contains(s)),
            "{differs:?}"
        );
        // Errors.
        let mut s = SegmentStream::new(reference.clone(), w, h, 2, false, &p).unwrap();
        assert!(s.push(&scaled[0][1..]).is_err());
        s.push(&scaled[0]).unwrap();
        assert_eq!(s.finish(), Err(VolumeError::Length { expected: 2, got: 1 }));
        s.push(&scaled[1]).unwrap();
        assert!(s.push(&scaled[2]).is_err());
        assert!(SegmentStream::new(reference.clone(), w, h + 1, 2, false, &p).is_err());
    }
}
