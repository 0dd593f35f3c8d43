//! Triangle meshes: PLY out (read back, with any other tool's PLY or OBJ, by
//! `lightrig_host::mesh_file`), marching cubes on a scalar grid, the volume a closed mesh
//! encloses, and the symmetric distance between two surfaces.

use std::collections::HashMap;
use std::fmt;
use std::io::{self, Write};
use std::sync::OnceLock;

use rayon::prelude::*;

use crate::vec3::{add, cross, dot, norm, scale, sub, V3};

/// An indexed triangle mesh, millimetres; triangles wind counter-clockwise seen from outside.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<V3>,
    /// Vertex indices, three per triangle.
    pub triangles: Vec<[u32; 3]>,
}

/// Writes `mesh` as binary little-endian PLY (float vertices, `uchar`-counted `int` faces), the
/// form MeshLab, Blender and Open3D read.
pub fn write_ply(mesh: &Mesh, out: &mut impl Write) -> io::Result<()> {
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment lightrig\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    )?;
    let mut buf = Vec::with_capacity(mesh.vertices.len() * 12 + mesh.triangles.len() * 13);
    for v in &mesh.vertices {
        for c in v {
            buf.extend_from_slice(&(*c as f32).to_le_bytes());
        }
    }
    for t in &mesh.triangles {
        buf.push(3);
        for i in t {
            buf.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    out.write_all(&buf)
}

// ---------------------------------------------------------------------------------------------
// Marching cubes
// ---------------------------------------------------------------------------------------------

/// A regular grid of samples: sample `(i, j, k)` (x fastest, then y, then z) sits at
/// `origin + (i·voxel[0], j·voxel[1], k·voxel[2])`, millimetres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Samples along x, y, z.
    pub dims: [usize; 3],
    /// Sample spacing along x, y, z.
    pub voxel: V3,
    /// Position of sample `(0, 0, 0)`.
    pub origin: V3,
}

impl Grid {
    /// Number of samples, `None` on overflow.
    pub fn len(&self) -> Option<usize> {
        self.dims[0].checked_mul(self.dims[1])?.checked_mul(self.dims[2])
    }

    /// Whether the grid has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == Some(0)
    }

    fn check(&self) -> Result<usize, GridError> {
        if self.dims.iter().any(|&d| d < 2) {
            return Err(GridError::TooSmall(self.dims));
        }
        if self.voxel.iter().any(|&v| !(v.is_finite() && v > 0.0))
            || self.origin.iter().any(|v| !v.is_finite())
        {
            return Err(GridError::BadSpacing);
        }
        // Vertex indices are u32 and a slab adds at most 4 vertices per sample (3 edges, 1 centre).
        let slice = self.dims[0].checked_mul(self.dims[1]).filter(|&s| s <= (u32::MAX / 4) as usize);
        slice.and(self.len()).ok_or(GridError::TooLarge(self.dims))
    }
}

/// Why a grid was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GridError {
    /// A dimension under 2: no cell to march.
    TooSmall([usize; 3]),
    /// More samples than can be indexed.
    TooLarge([usize; 3]),
    /// A voxel size that is not finite and positive, or an origin that is not finite.
    BadSpacing,
    /// A value array or slice of the wrong length.
    Length {
        /// Samples expected.
        expected: usize,
        /// Samples given.
        got: usize,
    },
    /// More slices pushed than `dims[2]`.
    TooManySlices,
    /// [`MarchingCubes::finish`] before all `dims[2]` slices came.
    MissingSlices {
        /// Slices expected.
        expected: usize,
        /// Slices pushed.
        got: usize,
    },
    /// The mesh outgrew `u32` vertex indices.
    TooManyVertices,
}

impl fmt::Display for GridError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GridError::TooSmall(d) => write!(f, "grid {d:?} needs at least 2 samples per axis"),
            GridError::TooLarge(d) => write!(f, "grid {d:?} is too large"),
            GridError::BadSpacing => write!(f, "voxel size must be finite and positive, origin finite"),
            GridError::Length { expected, got } => write!(f, "expected {expected} samples, got {got}"),
            GridError::TooManySlices => write!(f, "more slices than the grid's z size"),
            GridError::MissingSlices { expected, got } => write!(f, "expected {expected} slices, got {got}"),
            GridError::TooManyVertices => write!(f, "mesh exceeds 2^32 vertices"),
        }
    }
}

impl std::error::Error for GridError {}

/// Which side of the iso level is the solid (the mesh's inside).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solid {
    /// Values above the level are solid (occupancy, density).
    Above,
    /// Values below the level are solid (signed distance, negative inside).
    Below,
}

// Cube corners are numbered `c = dx | dy<<1 | dz<<2`. Edges: 0–3 run along x from corner
// `(0, dy, dz)` with `dy + 2dz = e`; 4–7 along y from `(dx, 0, dz)` with `dx + 2dz = e − 4`;
// 8–11 along z from `(dx, dy, 0)` with `dx + 2dy = e − 8`. Faces: `2·axis + side`.

fn edge_ends(e: usize) -> (usize, usize) {
    match e {
        0..=3 => {
            let (dy, dz) = (e & 1, e >> 1);
            (dy << 1 | dz << 2, 1 | dy << 1 | dz << 2)
        }
        4..=7 => {
            let (dx, dz) = ((e - 4) & 1, (e - 4) >> 1);
            (dx | dz << 2, dx | 2 | dz << 2)
        }
        _ => {
            let (dx, dy) = ((e - 8) & 1, (e - 8) >> 1);
            (dx | dy << 1, dx | dy << 1 | 4)
        }
    }
}

fn edge_between(a: usize, b: usize) -> usize {
    (0..12).find(|&e| edge_ends(e) == (a.min(b), a.max(b))).unwrap_or(0)
}

/// The face's corners in cyclic order: `(u, v) = (0,0), (1,0), (1,1), (0,1)` over its two
/// other axes in increasing order, so both cubes sharing a face list it alike.
fn face_corners(f: usize) -> [usize; 4] {
    let (axis, side) = (f / 2, f % 2);
    let (ua, va) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let c = |u: usize, v: usize| side << axis | u << ua | v << va;
    [c(0, 0), c(1, 0), c(1, 1), c(0, 1)]
}

fn corner_pos(c: usize) -> [f64; 3] {
    [(c & 1) as f64, (c >> 1 & 1) as f64, (c >> 2 & 1) as f64]
}

/// The case tables, generated at first use from the rules below rather than typed in.
///
/// Each face with two crossed edges joins them. A face with four (alternating corners) is
/// ambiguous; at run time the asymptotic decider (Nielson & Hamann 1991) says whether its
/// bilinear saddle is solid: if so the two solid corners are joined across the face and the
/// segments cut off the two empty corners, otherwise they cut off the solid ones. The decision
/// depends on the face's four values alone, so both cubes sharing it cut it alike and the
/// surface is closed. The segments of a cube link into cycles (each crossed edge lies on two
/// faces); each cycle is oriented so that the solid lies behind it and triangulated without a
/// diagonal between two vertices of one ambiguous face (the neighbour cube may own that
/// diagonal too, which would put a third and fourth triangle on it); where no such
/// triangulation exists, the cycle is fanned from a vertex added at its centroid.
struct Tables {
    /// Per case, the faces with four crossed edges (bit per face).
    ambiguous: [u8; 256],
    /// Triangles (cube edges, oriented) of case `config·64 + decisions` are
    /// `tris[offsets[i]..offsets[i + 1]]`.
    offsets: Vec<u32>,
    tris: Vec<[u8; 3]>,
    /// Per case, the edges of the cycle fanned from an extra centre vertex ([`CENTRE`] in
    /// `tris`), or 0.
    centre: Vec<u16>,
    /// Cases with two cycles that need a centre vertex (the run time makes one; should be none).
    #[cfg_attr(not(test), allow(dead_code))]
    compromised: usize,
}

/// The cube "edge" standing for a case's centre vertex in [`Tables::tris`].
const CENTRE: usize = 12;

fn tables() -> &'static Tables {
    static T: OnceLock<Tables> = OnceLock::new();
    T.get_or_init(build_tables)
}

fn build_tables() -> Tables {
    let faces: Vec<[usize; 4]> = (0..6).map(face_corners).collect();
    let face_edges: Vec<[usize; 4]> =
        faces.iter().map(|c| std::array::from_fn(|k| edge_between(c[k], c[(k + 1) % 4]))).collect();
    let mut ambiguous = [0u8; 256];
    let mut offsets = vec![0u32];
    let mut tris = Vec::new();
    let mut centre = Vec::with_capacity(256 * 64);
    let mut compromised = 0;
    #[allow(clippy::needless_range_loop)] // `config` is the case's bits, not only an index
    for config in 0..256usize {
        let solid = |c: usize| config >> c & 1 == 1;
        for (f, fc) in faces.iter().enumerate() {
            if (0..4).all(|k| solid(fc[k]) != solid(fc[(k + 1) % 4])) {
                ambiguous[config] |= 1 << f;
            }
        }
        for decisions in 0..64usize {
            let mut partners = [[usize::MAX; 2]; 12];
            let mut link = |a: usize, b: usize| {
                for (x, y) in [(a, b), (b, a)] {
                    let p = &mut partners[x];
                    if p[0] == usize::MAX {
                        p[0] = y;
                    } else {
                        p[1] = y;
                    }
                }
            };
            for (f, fc) in faces.iter().enumerate() {
                let fe = &face_edges[f];
                let crossed: Vec<usize> =
                    (0..4).filter(|&k| solid(fc[k]) != solid(fc[(k + 1) % 4])).collect();
                if crossed.len() == 2 {
                    link(fe[crossed[0]], fe[crossed[1]]);
                } else if crossed.len() == 4 {
                    let joined = decisions >> f & 1 == 1;
                    for k in 0..4 {
                        if solid(fc[k]) != joined {
                            // Cut off corner k: join its two face edges.
                            link(fe[(k + 3) % 4], fe[k]);
                        }
                    }
                }
            }
            let shares_ambiguous_face = |a: usize, b: usize| {
                (0..6).any(|f| {
                    ambiguous[config] >> f & 1 == 1
                        && face_edges[f].contains(&a)
                        && face_edges[f].contains(&b)
                })
            };
            let mut seen = [false; 12];
            let mut centre_mask = 0u16;
            for start in 0..12 {
                if seen[start] || partners[start][0] == usize::MAX {
                    continue;
                }
                let mut cycle = vec![start];
                seen[start] = true;
                let (mut prev, mut cur) = (start, partners[start][0]);
                while cur != start && cur != usize::MAX && cycle.len() <= 12 {
                    cycle.push(cur);
                    seen[cur] = true;
                    let next = if partners[cur][0] != prev { partners[cur][0] } else { partners[cur][1] };
                    (prev, cur) = (cur, next);
                }
                if cycle.len() < 3 {
                    continue;
                }
                if !oriented(&cycle, solid) {
                    cycle.reverse();
                }
                let t = match triangulate(&cycle, &shares_ambiguous_face) {
                    Some(t) => t,
                    None => {
                        // No such triangulation (e.g. the 9-gon of three corners that are
                        // pairwise face-diagonal): fan from a vertex at the cycle's centroid.
                        if centre_mask != 0 {
                            compromised += 1;
                        }
                        centre_mask = cycle.iter().fold(0u16, |m, &e| m | 1 << e);
                        (0..cycle.len()).map(|k| [CENTRE, cycle[k], cycle[(k + 1) % cycle.len()]]).collect()
                    }
                };
                tris.extend(t.iter().map(|t| t.map(|e| e as u8)));
            }
            offsets.push(tris.len() as u32);
            centre.push(centre_mask);
        }
    }
    Tables { ambiguous, offsets, tris, centre, compromised }
}

/// Whether the cycle runs counter-clockwise seen from the empty side. Take its first segment,
/// `d` from edge `a`'s midpoint to edge `b`'s, on the cube face with outward normal `n`, and
/// `s` along edge `a` from its empty end to its solid end (across the segment, into the solid).
/// The polygon lies inside the cube, to the left of `d` seen from the outward side of a
/// counter-clockwise loop; that holds iff `(s × d)·n > 0` (checked by the signed volumes in
/// the tests).
fn oriented(cycle: &[usize], solid: impl Fn(usize) -> bool) -> bool {
    let (a, b) = (cycle[0], cycle[1]);
    let mid = |e: usize| {
        let (p, q) = edge_ends(e);
        scale(add(corner_pos(p), corner_pos(q)), 0.5)
    };
    let (p, q) = edge_ends(a);
    let s = if solid(p) { sub(corner_pos(p), corner_pos(q)) } else { sub(corner_pos(q), corner_pos(p)) };
    let d = sub(mid(b), mid(a));
    // The face holding both edges, and its outward normal.
    let (pb, qb) = edge_ends(b);
    let face = (0..6).find(|&f| {
        let c = face_corners(f);
        [p, q, pb, qb].iter().all(|x| c.contains(x))
    });
    let Some(f) = face else { return true };
    let mut n = [0.0; 3];
    n[f / 2] = if f % 2 == 1 { 1.0 } else { -1.0 };
    dot(cross(s, d), n) > 0.0
}

/// Triangulates the cycle `p` (kept in order) with no diagonal for which `bad` holds.
fn triangulate(p: &[usize], bad: &impl Fn(usize, usize) -> bool) -> Option<Vec<[usize; 3]>> {
    let n = p.len();
    if n == 3 {
        return Some(vec![[p[0], p[1], p[2]]]);
    }
    // Triangle (p0, pk, p_{n−1}) on the closing edge, then the two sides.
    for k in 1..n - 1 {
        if (k > 1 && bad(p[0], p[k])) || (k < n - 2 && bad(p[k], p[n - 1])) {
            continue;
        }
        let mut out = vec![[p[0], p[k], p[n - 1]]];
        if k > 1 {
            match triangulate(&p[..=k], bad) {
                Some(t) => out.extend(t),
                None => continue,
            }
        }
        if k < n - 2 {
            match triangulate(&p[k..], bad) {
                Some(t) => out.extend(t),
                None => continue,
            }
        }
        return Some(out);
    }
    None
}

/// One z-slice's state: sign-adjusted values (`> 0` is solid), solid bytes, the 4-bit corner
/// code of each cell square (bit `dx | dy<<1`), whether that square is mixed (code not 0 or
/// 15), and the vertex on each crossed x- and y-edge. The byte arrays let the scans skip
/// eight uniform samples or cells per comparison.
#[derive(Default)]
struct Slice {
    f: Vec<f32>,
    solid: Vec<u8>,
    code: Vec<u8>,
    mixed: Vec<u8>,
    xe: Vec<u32>,
    ye: Vec<u32>,
}

/// Streaming marching cubes: push the grid's z-slices in order, then [`finish`](Self::finish).
/// Memory is the mesh plus two slices (values, codes and edge vertices).
pub struct MarchingCubes {
    grid: Grid,
    iso: f32,
    sign: f32,
    z0: usize,
    taken: usize,
    lo: Slice,
    hi: Slice,
    ze: Vec<u32>,
    mesh: Mesh,
    /// Vertices on the first slice's edges (emitted first).
    first_count: usize,
    /// Vertices on the last slice's x- and y-edges.
    last: std::ops::Range<usize>,
}

impl MarchingCubes {
    /// Marching cubes over `grid` at level `iso`; `solid` says which side is inside. The
    /// triangles wind counter-clockwise seen from outside (outward normals), vertices are
    /// shared between cells, and the surface is closed wherever the solid stays inside the grid.
    pub fn new(grid: Grid, iso: f32, solid: Solid) -> Result<Self, GridError> {
        Self::starting_at(grid, iso, solid, 0)
    }

    fn starting_at(grid: Grid, iso: f32, solid: Solid, z0: usize) -> Result<Self, GridError> {
        grid.check()?;
        let n = grid.dims[0] * grid.dims[1];
        let slice = || Slice {
            f: vec![0.0; n],
            solid: vec![0; n],
            code: vec![0; n],
            mixed: vec![0; n],
            xe: vec![0; n],
            ye: vec![0; n],
        };
        Ok(MarchingCubes {
            grid,
            iso,
            sign: if solid == Solid::Above { 1.0 } else { -1.0 },
            z0,
            taken: 0,
            lo: slice(),
            hi: slice(),
            ze: vec![0; n],
            mesh: Mesh::default(),
            first_count: 0,
            last: 0..0,
        })
    }

    /// Takes the next z-slice (`dims[0]·dims[1]` values, x fastest).
    pub fn push(&mut self, values: &[f32]) -> Result<(), GridError> {
        let [nx, ny, nz] = self.grid.dims;
        if values.len() != nx * ny {
            return Err(GridError::Length { expected: nx * ny, got: values.len() });
        }
        if self.z0 + self.taken >= nz {
            return Err(GridError::TooManySlices);
        }
        if self.mesh.vertices.len() + 4 * nx * ny > u32::MAX as usize {
            return Err(GridError::TooManyVertices);
        }
        let k = self.z0 + self.taken;
        load(&mut self.hi, values, self.iso, self.sign, nx, ny);
        let start = self.mesh.vertices.len();
        xy_vertices(&mut self.hi, &self.grid, k, &mut self.mesh.vertices);
        self.last = start..self.mesh.vertices.len();
        if self.taken == 0 {
            self.first_count = self.mesh.vertices.len();
        } else {
            self.slab(k - 1);
        }
        std::mem::swap(&mut self.lo, &mut self.hi);
        self.taken += 1;
        Ok(())
    }

    /// The mesh, once all `dims[2]` slices have been pushed.
    pub fn finish(self) -> Result<Mesh, GridError> {
        let expected = self.grid.dims[2];
        if self.taken != expected {
            return Err(GridError::MissingSlices { expected, got: self.taken });
        }
        Ok(self.mesh)
    }

    /// The cells between slice `k` (in `lo`) and `k + 1` (in `hi`).
    fn slab(&mut self, k: usize) {
        let [nx, ny, _] = self.grid.dims;
        let (lo, hi, g) = (&self.lo, &self.hi, &self.grid);
        let verts = &mut self.mesh.vertices;
        // Vertices on the z-edges.
        let z = g.origin[2] + k as f64 * g.voxel[2];
        let ze = &mut self.ze;
        each_difference(&lo.solid, &hi.solid, 0, |p| {
            let (i, j) = (p % nx, p / nx);
            ze[p] = verts.len() as u32;
            let (a, b) = (lo.f[p], hi.f[p]);
            let x = g.origin[0] + i as f64 * g.voxel[0];
            let y = g.origin[1] + j as f64 * g.voxel[1];
            verts.push([x, y, z + crossing(a, b) * g.voxel[2]]);
        });
        let t = tables();
        let ze = &self.ze;
        let tris = &mut self.mesh.triangles;
        // Cells with a crossing: the square codes differ between the slices, or are mixed.
        let cells = (ny - 1) * nx;
        each_nonzero(&lo.code[..cells], &hi.code[..cells], &lo.mixed[..cells], |c| {
            if c % nx == nx - 1 {
                return; // the unused last column
            }
            let config = (lo.code[c] | hi.code[c] << 4) as usize;
            let mut decisions = 0;
            let amb = t.ambiguous[config];
            if amb != 0 {
                let v = |corner: usize| {
                    let s = if corner & 4 == 0 { &lo.f } else { &hi.f };
                    s[c + (corner & 1) + (corner >> 1 & 1) * nx]
                };
                for f in 0..6 {
                    if amb >> f & 1 == 1 {
                        let [p0, p1, p2, p3] = face_corners(f);
                        let (f0, f1, f2, f3) = (v(p0), v(p1), v(p2), v(p3));
                        let n = f0 * f2 - f1 * f3;
                        let joined = if f0 > 0.0 { n > 0.0 } else { n < 0.0 };
                        decisions |= (joined as usize) << f;
                    }
                }
            }
            let mut ev = [
                lo.xe[c],
                lo.xe[c + nx],
                hi.xe[c],
                hi.xe[c + nx],
                lo.ye[c],
                lo.ye[c + 1],
                hi.ye[c],
                hi.ye[c + 1],
                ze[c],
                ze[c + 1],
                ze[c + nx],
                ze[c + nx + 1],
                0,
            ];
            let case = config * 64 + decisions;
            let centre = t.centre[case];
            if centre != 0 {
                let (mut sum, mut count) = ([0.0; 3], 0.0);
                for (e, &v) in ev.iter().enumerate().take(12) {
                    if centre >> e & 1 == 1 {
                        sum = add(sum, verts[v as usize]);
                        count += 1.0;
                    }
                }
                ev[CENTRE] = verts.len() as u32;
                verts.push(scale(sum, 1.0 / count));
            }
            let (s, e) = (t.offsets[case] as usize, t.offsets[case + 1] as usize);
            for tri in &t.tris[s..e] {
                tris.push([ev[tri[0] as usize], ev[tri[1] as usize], ev[tri[2] as usize]]);
            }
        });
    }
}

/// Calls `f(offset + i)` for each `i` where `a[i] != b[i]`, comparing eight bytes at a time.
#[inline]
fn each_difference(a: &[u8], b: &[u8], offset: usize, mut f: impl FnMut(usize)) {
    let n = a.len().min(b.len());
    let (mut ca, mut cb) = (a[..n].chunks_exact(8), b[..n].chunks_exact(8));
    let mut i = 0;
    for (wa, wb) in (&mut ca).zip(&mut cb) {
        let x = word(wa) ^ word(wb);
        if x != 0 {
            set_bytes(x, |k| f(offset + i + k));
        }
        i += 8;
    }
    for (k, (x, y)) in ca.remainder().iter().zip(cb.remainder()).enumerate() {
        if x != y {
            f(offset + i + k);
        }
    }
}

/// Calls `f(i)` for each `i` where `a[i] != b[i]` or `m[i] != 0`.
#[inline]
fn each_nonzero(a: &[u8], b: &[u8], m: &[u8], mut f: impl FnMut(usize)) {
    let n = a.len().min(b.len()).min(m.len());
    let mut i = 0;
    while i + 8 <= n {
        let x = (word(&a[i..i + 8]) ^ word(&b[i..i + 8])) | word(&m[i..i + 8]);
        if x != 0 {
            set_bytes(x, |k| f(i + k));
        }
        i += 8;
    }
    for k in i..n {
        if a[k] != b[k] || m[k] != 0 {
            f(k);
        }
    }
}

#[inline]
fn word(b: &[u8]) -> u64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[..8]);
    u64::from_le_bytes(w)
}

/// Calls `f(k)` for each non-zero byte `k` of `x`, lowest first.
#[inline]
fn set_bytes(mut x: u64, mut f: impl FnMut(usize)) {
    while x != 0 {
        let k = (x.trailing_zeros() / 8) as usize;
        f(k);
        x &= !(0xFFu64 << (8 * k));
    }
}

/// Where along an edge from value `a` to `b` the level (0) is crossed, in [0, 1].
#[inline]
fn crossing(a: f32, b: f32) -> f64 {
    let t = a / (a - b);
    if t.is_finite() {
        t.clamp(0.0, 1.0) as f64
    } else {
        0.5
    }
}

/// Fills a slice's sign-adjusted values and cell codes. NaN counts as empty and infinities are
/// clamped, so every crossing lies on its edge.
fn load(s: &mut Slice, values: &[f32], iso: f32, sign: f32, nx: usize, ny: usize) {
    for ((f, b), &v) in s.f.iter_mut().zip(s.solid.iter_mut()).zip(values) {
        let x = sign * (v - iso);
        *f = if x.is_nan() { -f32::MAX } else { x.clamp(-f32::MAX, f32::MAX) };
        *b = (*f > 0.0) as u8;
    }
    for j in 0..ny - 1 {
        let (r0, r1) = (&s.solid[j * nx..(j + 1) * nx], &s.solid[(j + 1) * nx..(j + 2) * nx]);
        let code = &mut s.code[j * nx..(j + 1) * nx - 1];
        let mixed = &mut s.mixed[j * nx..(j + 1) * nx - 1];
        for i in 0..nx - 1 {
            let c = r0[i] | r0[i + 1] << 1 | r1[i] << 2 | r1[i + 1] << 3;
            code[i] = c;
            mixed[i] = (c != 0 && c != 15) as u8;
        }
    }
}

/// Vertices on the crossed x- and y-edges of slice `k`.
fn xy_vertices(s: &mut Slice, g: &Grid, k: usize, verts: &mut Vec<V3>) {
    let [nx, ny, _] = g.dims;
    let z = g.origin[2] + k as f64 * g.voxel[2];
    for j in 0..ny {
        let y = g.origin[1] + j as f64 * g.voxel[1];
        let row = j * nx;
        let (f, xe) = (&s.f, &mut s.xe);
        each_difference(&s.solid[row..row + nx - 1], &s.solid[row + 1..row + nx], row, |p| {
            xe[p] = verts.len() as u32;
            let x = g.origin[0] + (p - row) as f64 * g.voxel[0];
            verts.push([x + crossing(f[p], f[p + 1]) * g.voxel[0], y, z]);
        });
        if j + 1 < ny {
            let ye = &mut s.ye;
            each_difference(&s.solid[row..row + nx], &s.solid[row + nx..row + 2 * nx], row, |p| {
                ye[p] = verts.len() as u32;
                let x = g.origin[0] + (p - row) as f64 * g.voxel[0];
                verts.push([x, y + crossing(f[p], f[p + nx]) * g.voxel[1], z]);
            });
        }
    }
}

/// Marching cubes over a whole grid (`values` x fastest, then y, then z); see
/// [`MarchingCubes`]. Runs in z-chunks on rayon's threads and joins them on the shared slice,
/// giving exactly the mesh the streaming form gives.
pub fn marching_cubes(values: &[f32], grid: &Grid, iso: f32, solid: Solid) -> Result<Mesh, GridError> {
    let len = grid.check()?;
    if values.len() != len {
        return Err(GridError::Length { expected: len, got: values.len() });
    }
    let [nx, ny, nz] = grid.dims;
    let n = nx * ny;
    let slabs = nz - 1;
    // A few chunks per thread evens out the surface's uneven spread over z.
    let chunks = (rayon::current_num_threads() * 4).clamp(1, slabs);
    let parts: Vec<Result<MarchingCubes, GridError>> = (0..chunks)
        .into_par_iter()
        .map(|c| {
            let (z0, z1) = (c * slabs / chunks, (c + 1) * slabs / chunks);
            let mut mc = MarchingCubes::starting_at(*grid, iso, solid, z0)?;
            for k in z0..=z1 {
                mc.push(&values[k * n..(k + 1) * n])?;
            }
            Ok(mc)
        })
        .collect();
    let parts = parts.into_iter().collect::<Result<Vec<_>, _>>()?;
    let total: usize = parts
        .iter()
        .enumerate()
        .map(|(c, p)| p.mesh.vertices.len() - if c > 0 { p.first_count } else { 0 })
        .sum();
    if total > u32::MAX as usize {
        return Err(GridError::TooManyVertices);
    }
    let mut mesh = Mesh {
        vertices: Vec::with_capacity(total),
        triangles: Vec::with_capacity(parts.iter().map(|p| p.mesh.triangles.len()).sum()),
    };
    // Chunk c's first slice is chunk c−1's last: same values, same edge order, same vertices.
    let mut shared_base = 0u32;
    for (c, p) in parts.into_iter().enumerate() {
        let skip = if c > 0 { p.first_count } else { 0 };
        let base = mesh.vertices.len() as u32;
        let last_start = base + (p.last.start - skip) as u32;
        mesh.vertices.extend_from_slice(&p.mesh.vertices[skip..]);
        let (sb, skip32) = (shared_base, skip as u32);
        mesh.triangles.extend(
            p.mesh.triangles.iter().map(|t| t.map(|i| if i < skip32 { sb + i } else { base + i - skip32 })),
        );
        shared_base = last_start;
    }
    Ok(mesh)
}

// ---------------------------------------------------------------------------------------------
// Measures
// ---------------------------------------------------------------------------------------------

/// The volume a closed, outward-wound mesh encloses (divergence theorem: the sum of the signed
/// tetrahedra from a reference point to each triangle), mm³. Negative when wound inward.
pub fn enclosed_volume(mesh: &Mesh) -> f64 {
    // Measured from the first vertex rather than the origin, so far-off meshes keep precision.
    let Some(&o) = mesh.vertices.first() else { return 0.0 };
    let at = |i: u32| mesh.vertices.get(i as usize).map(|&v| sub(v, o));
    mesh.triangles.iter().filter_map(|t| Some(dot(at(t[0])?, cross(at(t[1])?, at(t[2])?)))).sum::<f64>() / 6.0
}

/// How far a mesh is from a closed, consistently oriented 2-manifold, by edges.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EdgeDefects {
    /// Edges with one triangle (holes).
    pub boundary: usize,
    /// Edges with more than two triangles.
    pub non_manifold: usize,
    /// Edges with two triangles that run it the same way (a flipped neighbour).
    pub misoriented: usize,
    /// Triangles that repeat a vertex.
    pub degenerate: usize,
}

impl EdgeDefects {
    /// Whether the mesh is closed and oriented: every edge in exactly two triangles, once each way.
    pub fn is_closed(&self) -> bool {
        *self == EdgeDefects::default()
    }
}

/// Counts the mesh's edge defects; a watertight, consistently oriented mesh has none.
pub fn edge_defects(mesh: &Mesh) -> EdgeDefects {
    let mut uses: HashMap<(u32, u32), (u32, u32)> = HashMap::with_capacity(mesh.triangles.len() * 3 / 2);
    let mut d = EdgeDefects::default();
    for t in &mesh.triangles {
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            d.degenerate += 1;
            continue;
        }
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let e = uses.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                e.0 += 1;
            } else {
                e.1 += 1;
            }
        }
    }
    for &(f, b) in uses.values() {
        match f + b {
            1 => d.boundary += 1,
            2 if f != 1 => d.misoriented += 1,
            2 => {}
            _ => d.non_manifold += 1,
        }
    }
    d
}

/// Distance from `p` to the triangle `(a, b, c)`: the closest point found by the triangle's
/// Voronoi regions (vertex, edge, face), so it is exact for any triangle shape.
pub fn point_triangle_distance(p: V3, a: V3, b: V3, c: V3) -> f64 {
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return norm(ap);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return norm(bp);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let t = d1 / (d1 - d3);
        return norm(sub(p, add(a, scale(ab, t))));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return norm(cp);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let t = d2 / (d2 - d6);
        return norm(sub(p, add(a, scale(ac, t))));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
        let t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return norm(sub(p, add(b, scale(sub(c, b), t))));
    }
    let den = va + vb + vc;
    if den.abs() < f64::MIN_POSITIVE {
        // Degenerate (zero-area) triangle: its edges are all there is.
        return norm(sub(p, a)).min(norm(sub(p, b))).min(norm(sub(p, c)));
    }
    let (v, w) = (vb / den, vc / den);
    norm(sub(p, add(a, add(scale(ab, v), scale(ac, w)))))
}

/// A mesh's triangles bucketed in a uniform grid, for nearest-surface queries.
pub struct TriangleGrid<'a> {
    mesh: &'a Mesh,
    lo: V3,
    cell: f64,
    dims: [usize; 3],
    start: Vec<u32>,
    items: Vec<u32>,
}

impl<'a> TriangleGrid<'a> {
    /// Buckets `mesh`'s triangles (by bounding box) in cells about twice the mean edge long.
    /// `None` for a mesh without triangles or with an index out of range or a non-finite vertex.
    pub fn new(mesh: &'a Mesh) -> Option<Self> {
        if mesh.triangles.is_empty()
            || mesh.triangles.iter().flatten().any(|&i| i as usize >= mesh.vertices.len())
            || mesh.vertices.iter().flatten().any(|c| !c.is_finite())
        {
            return None;
        }
        let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
        let mut edge = 0.0;
        for t in &mesh.triangles {
            for k in 0..3 {
                let v = mesh.vertices[t[k] as usize];
                edge += norm(sub(v, mesh.vertices[t[(k + 1) % 3] as usize]));
                for a in 0..3 {
                    lo[a] = lo[a].min(v[a]);
                    hi[a] = hi[a].max(v[a]);
                }
            }
        }
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        // Two mean edges, but no more than ~64 cells per triangle overall.
        let mut cell = (2.0 * edge / (3 * mesh.triangles.len()) as f64).max(extent / 1024.0).max(1e-9);
        let count = |cell: f64| (0..3).map(|a| ((hi[a] - lo[a]) / cell) as usize + 1).product::<usize>();
        while count(cell) > 64 * mesh.triangles.len() + 64 {
            cell *= 1.5;
        }
        let dims: [usize; 3] = std::array::from_fn(|a| ((hi[a] - lo[a]) / cell) as usize + 1);
        let index = |p: V3| -> [usize; 3] {
            std::array::from_fn(|a| (((p[a] - lo[a]) / cell).max(0.0) as usize).min(dims[a] - 1))
        };
        let ranges: Vec<([usize; 3], [usize; 3])> = mesh
            .triangles
            .iter()
            .map(|t| {
                let vs = t.map(|i| mesh.vertices[i as usize]);
                let bl = std::array::from_fn(|a| vs[0][a].min(vs[1][a]).min(vs[2][a]));
                let bh = std::array::from_fn(|a| vs[0][a].max(vs[1][a]).max(vs[2][a]));
                (index(bl), index(bh))
            })
            .collect();
        let flat = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
        let ncell = dims[0] * dims[1] * dims[2];
        let mut start = vec![0u32; ncell + 1];
        let each = |(l, h): &([usize; 3], [usize; 3]), f: &mut dyn FnMut(usize)| {
            for z in l[2]..=h[2] {
                for y in l[1]..=h[1] {
                    for x in l[0]..=h[0] {
                        f(flat([x, y, z]));
                    }
                }
            }
        };
        for r in &ranges {
            each(r, &mut |c| start[c + 1] += 1);
        }
        for c in 0..ncell {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; start[ncell] as usize];
        for (t, r) in ranges.iter().enumerate() {
            each(r, &mut |c| {
                items[fill[c] as usize] = t as u32;
                fill[c] += 1;
            });
        }
        Some(TriangleGrid { mesh, lo, cell, dims, start, items })
    }

    /// Distance from `p` to the nearest triangle. Searches shells of cells outwards and stops
    /// once the best distance is within the shell's guaranteed minimum.
    pub fn distance(&self, p: V3) -> f64 {
        let c: [isize; 3] = std::array::from_fn(|a| {
            (((p[a] - self.lo[a]) / self.cell).max(0.0) as usize).min(self.dims[a] - 1) as isize
        });
        let mut best = f64::MAX;
        let max_r = self.dims.iter().copied().max().unwrap_or(1) as isize;
        for r in 0..=max_r {
            for z in c[2] - r..=c[2] + r {
                for y in c[1] - r..=c[1] + r {
                    for x in c[0] - r..=c[0] + r {
                        let on_shell =
                            (x - c[0]).abs() == r || (y - c[1]).abs() == r || (z - c[2]).abs() == r;
                        if !on_shell
                            || [x, y, z].iter().zip(self.dims).any(|(&v, d)| v < 0 || v >= d as isize)
                        {
                            continue;
                        }
                        let f = ((z as usize * self.dims[1]) + y as usize) * self.dims[0] + x as usize;
                        for &t in &self.items[self.start[f] as usize..self.start[f + 1] as usize] {
                            let [a, b, cc] =
                                self.mesh.triangles[t as usize].map(|i| self.mesh.vertices[i as usize]);
                            best = best.min(point_triangle_distance(p, a, b, cc));
                        }
                    }
                }
            }
            // Anything beyond shell r is at least r cells away.
            if best <= r as f64 * self.cell {
                break;
            }
        }
        best
    }
}

/// Symmetric surface distance between two meshes, mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceDistance {
    /// Area-weighted mean over both surfaces.
    pub mean: f64,
    /// Area-weighted root mean square over both surfaces.
    pub rms: f64,
    /// Area-weighted 95th percentile over both surfaces (of the triangle centroids'
    /// distances).
    pub p95: f64,
    /// Largest distance from any sample (vertex or triangle centroid) of either surface to the
    /// other (a sampled Hausdorff distance).
    pub max: f64,
}

/// The symmetric surface distance between `a` and `b`: from each mesh's vertices and triangle
/// centroids to the other's triangles. The mean and RMS weight each centroid by its
/// triangle's area (so they are surface averages, not vertex averages); the maximum also
/// takes the vertices. `None` when either mesh has no usable triangles.
pub fn surface_distance(a: &Mesh, b: &Mesh) -> Option<SurfaceDistance> {
    let (ga, gb) = (TriangleGrid::new(a)?, TriangleGrid::new(b)?);
    let one_way = |from: &Mesh, to: &TriangleGrid| -> (Vec<(f64, f64)>, f64) {
        let tri: Vec<(f64, f64)> = from
            .triangles
            .par_iter()
            .map(|t| {
                let [p, q, r] = t.map(|i| from.vertices[i as usize]);
                let area = 0.5 * norm(cross(sub(q, p), sub(r, p)));
                (area, to.distance(scale(add(add(p, q), r), 1.0 / 3.0)))
            })
            .collect();
        let vmax = from.vertices.par_iter().map(|&v| to.distance(v)).reduce(|| 0.0, f64::max);
        (tri, vmax)
    };
    let (mut tri, ma) = one_way(a, &gb);
    let (tb, mb) = one_way(b, &ga);
    tri.extend(tb);
    let (w, s, s2) =
        tri.iter().fold((0.0, 0.0, 0.0), |(w, s, s2), &(a, d)| (w + a, s + a * d, s2 + a * d * d));
    if w <= 0.0 {
        return None;
    }
    let max = tri.iter().map(|t| t.1).fold(ma.max(mb), f64::max);
    tri.sort_unstable_by(|x, y| x.1.total_cmp(&y.1));
    let mut acc = 0.0;
    let p95 = tri
        .iter()
        .find(|t| {
            acc += t.0;
            acc >= 0.95 * w
        })
        .map_or(max, |t| t.1);
    Some(SurfaceDistance { mean: s / w, rms: (s2 / w).sqrt(), p95, max })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_bytes() {
        let m = Mesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2]],
        };
        let mut out = Vec::new();
        write_ply(&m, &mut out).unwrap();
        let header_end = out.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let body = &out[header_end..];
        assert_eq!(body.len(), 3 * 12 + 13);
        assert_eq!(&body[12..16], &1.0f32.to_le_bytes());
        assert_eq!(&body[36..], &[3, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]);
    }

    /// Samples `f` on a grid of `n³` unit voxels with origin `o`.
    fn sample(n: usize, o: V3, f: impl Fn(V3) -> f64) -> (Vec<f32>, Grid) {
        let g = Grid { dims: [n, n, n], voxel: [1.0; 3], origin: o };
        let mut v = Vec::with_capacity(n * n * n);
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    v.push(f([o[0] + i as f64, o[1] + j as f64, o[2] + k as f64]) as f32);
                }
            }
        }
        (v, g)
    }

    fn sphere_sdf(r: f64) -> impl Fn(V3) -> f64 {
        move |p| norm(p) - r
    }

    fn torus_sdf(big: f64, small: f64) -> impl Fn(V3) -> f64 {
        move |p| ((p[0] * p[0] + p[1] * p[1]).sqrt() - big).hypot(p[2]) - small
    }

    #[test]
    fn tables_are_consistent() {
        let t = tables();
        assert_eq!(t.compromised, 0, "a cycle needed a diagonal across an ambiguous face");
        assert_eq!(t.offsets.len(), 256 * 64 + 1);
        // The empty and full cubes have nothing; a single corner is one triangle.
        assert_eq!(t.offsets[1], 0);
        assert_eq!(t.offsets[64 + 1] - t.offsets[64], 1);
        assert_eq!(t.ambiguous[0b0000_0001], 0);
        // Each face is ambiguous in 2 of its 16 corner patterns, whatever the other 4 corners:
        // 6 faces · 2 · 16 = 192 ambiguous faces over the 256 cases.
        assert_eq!(t.ambiguous.iter().map(|a| a.count_ones()).sum::<u32>(), 192);
        // Only the cases whose cycle cannot avoid a diagonal across an ambiguous face get a
        // centre vertex; the unambiguous cases never do.
        assert!((0..256).filter(|&c| t.ambiguous[c] == 0).all(|c| t.centre[c * 64] == 0));
        assert!(t.centre.iter().any(|&m| m != 0));
    }

    #[test]
    fn sphere_on_surface_closed_and_volume() {
        let r = 12.0;
        let (v, g) = sample(30, [-14.5, -14.3, -14.1], sphere_sdf(r));
        let m = marching_cubes(&v, &g, 0.0, Solid::Below).unwrap();
        assert!(m.triangles.len() > 1000);
        // Linear interpolation of the exact distance along an edge: error ≤ h²/(2r) ≈ 0.04.
        let worst = m.vertices.iter().map(|&p| (norm(p) - r).abs()).fold(0.0, f64::max);
        assert!(worst < 0.03, "vertex off the sphere by {worst} voxels");
        assert!(edge_defects(&m).is_closed(), "{:?}", edge_defects(&m));
        let vol = enclosed_volume(&m);
        let truth = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
        assert!((vol / truth - 1.0).abs() < 0.01, "volume {vol} vs {truth}");
        // Chords cut inside a convex surface: slightly less than the truth.
        assert!(vol < truth);
    }

    #[test]
    fn torus_on_surface_closed_and_volume() {
        let (big, small) = (11.0, 5.0);
        let (v, g) = sample(36, [-17.5, -17.25, -17.7], torus_sdf(big, small));
        let m = marching_cubes(&v, &g, 0.0, Solid::Below).unwrap();
        let sdf = torus_sdf(big, small);
        let worst = m.vertices.iter().map(|&p| sdf(p).abs()).fold(0.0, f64::max);
        assert!(worst < 0.05, "vertex off the torus by {worst}");
        let d = edge_defects(&m);
        assert!(d.is_closed(), "{d:?}");
        // Euler characteristic of a torus: V − E + F = 0, with E = 3F/2 on a closed mesh.
        assert_eq!(m.vertices.len() as i64 - (m.triangles.len() / 2) as i64, 0);
        let vol = enclosed_volume(&m);
        let truth = 2.0 * std::f64::consts::PI.powi(2) * big * small * small;
        assert!((vol / truth - 1.0).abs() < 0.01, "volume {vol} vs {truth}");
    }

    #[test]
    fn solid_above_and_scaled_voxels() {
        // Occupancy-like field (positive inside) on anisotropic voxels: same sphere, outward
        // winding, volume in mm³.
        let r = 9.0;
        let g = Grid { dims: [40, 30, 24], voxel: [0.5, 0.7, 0.9], origin: [-10.0, -10.5, -10.8] };
        let mut v = Vec::new();
        for k in 0..24 {
            for j in 0..30 {
                for i in 0..40 {
                    let p = [-10.0 + 0.5 * i as f64, -10.5 + 0.7 * j as f64, -10.8 + 0.9 * k as f64];
                    v.push((r - norm(p)) as f32 + 3.0);
                }
            }
        }
        let m = marching_cubes(&v, &g, 3.0, Solid::Above).unwrap();
        assert!(edge_defects(&m).is_closed());
        let truth = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
        let vol = enclosed_volume(&m);
        assert!((vol / truth - 1.0).abs() < 0.01, "volume {vol} vs {truth}");
        let worst = m.vertices.iter().map(|&p| (norm(p) - r).abs()).fold(0.0, f64::max);
        assert!(worst < 0.05, "{worst}");
    }

    fn hash(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    #[test]
    fn noise_field_is_closed_manifold() {
        // White noise: every ambiguous face and interior configuration shows up. The border is
        // forced empty so every component is closed inside the grid.
        let n = 28;
        let g = Grid { dims: [n; 3], voxel: [1.0; 3], origin: [0.0; 3] };
        let mut v = vec![0f32; n * n * n];
        for (idx, x) in v.iter_mut().enumerate() {
            let (i, j, k) = (idx % n, idx / n % n, idx / n / n);
            let border = [i, j, k].iter().any(|&c| c == 0 || c == n - 1);
            *x =
                if border { -1.0 } else { (hash(idx as u64) >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0 };
        }
        // Count the cells with an ambiguous face so the test cannot pass vacuously.
        let t = tables();
        let mut amb = 0;
        for k in 0..n - 1 {
            for j in 0..n - 1 {
                for i in 0..n - 1 {
                    let mut c = 0;
                    for corner in 0..8 {
                        let (a, b, d) = (corner & 1, corner >> 1 & 1, corner >> 2);
                        c |= ((v[((k + d) * n + j + b) * n + i + a] > 0.0) as usize) << corner;
                    }
                    amb += (t.ambiguous[c] != 0) as usize;
                }
            }
        }
        assert!(amb > 2000, "only {amb} ambiguous cells");
        let m = marching_cubes(&v, &g, 0.0, Solid::Above).unwrap();
        let d = edge_defects(&m);
        assert!(d.is_closed(), "{d:?}");
        // Many closed components, each wound outward: the total is positive and roughly the
        // solid fraction (half the interior).
        let vol = enclosed_volume(&m);
        let interior = ((n - 2) as f64).powi(3);
        assert!(vol > 0.3 * interior && vol < 0.7 * interior, "volume {vol} of {interior}");
    }

    #[test]
    fn streaming_matches_parallel_and_bounds_errors() {
        let (v, g) = sample(33, [-16.0, -16.2, -16.4], torus_sdf(10.0, 4.0));
        let whole = marching_cubes(&v, &g, 0.0, Solid::Below).unwrap();
        let mut mc = MarchingCubes::new(g, 0.0, Solid::Below).unwrap();
        let n = 33 * 33;
        for k in 0..33 {
            mc.push(&v[k * n..(k + 1) * n]).unwrap();
        }
        assert_eq!(mc.push(&v[..n]), Err(GridError::TooManySlices));
        assert_eq!(mc.finish().unwrap(), whole);
        let mut short = MarchingCubes::new(g, 0.0, Solid::Below).unwrap();
        assert_eq!(short.push(&v[..n - 1]), Err(GridError::Length { expected: n, got: n - 1 }));
        short.push(&v[..n]).unwrap();
        assert!(matches!(short.finish(), Err(GridError::MissingSlices { expected: 33, got: 1 })));
        let flat = Grid { dims: [4, 4, 1], ..g };
        assert_eq!(marching_cubes(&v[..16], &flat, 0.0, Solid::Below), Err(GridError::TooSmall([4, 4, 1])));
        let bad = Grid { voxel: [1.0, 0.0, 1.0], ..g };
        assert_eq!(marching_cubes(&v, &bad, 0.0, Solid::Below), Err(GridError::BadSpacing));
        assert!(matches!(marching_cubes(&v[1..], &g, 0.0, Solid::Below), Err(GridError::Length { .. })));
        // NaN and infinities do not break the surface.
        let mut w = v.clone();
        w[5] = f32::NAN;
        w[n * 16 + 33 * 16 + 6] = f32::NEG_INFINITY;
        let m = marching_cubes(&w, &g, 0.0, Solid::Below).unwrap();
        assert!(m.vertices.iter().flatten().all(|c| c.is_finite()));
    }

    #[test]
    fn point_triangle_distances() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]);
        let d = |p| point_triangle_distance(p, a, b, c);
        assert!((d([0.5, 0.5, 3.0]) - 3.0).abs() < 1e-12); // face
        assert!((d([-1.0, -1.0, 0.0]) - 2f64.sqrt()).abs() < 1e-12); // vertex a
        assert!((d([1.0, -2.0, 0.0]) - 2.0).abs() < 1e-12); // edge ab
        assert!((d([2.0, 2.0, 0.0]) - 2f64.sqrt()).abs() < 1e-12); // edge bc
        assert!((d([3.0, 0.0, 4.0]) - 17f64.sqrt()).abs() < 1e-12); // vertex b
    }

    #[test]
    fn surface_distance_of_concentric_spheres() {
        // Two spheres 0.5 apart: every sample is ≈ 0.5 from the other surface.
        let (v, g) = sample(30, [-14.5; 3], sphere_sdf(10.0));
        let a = marching_cubes(&v, &g, 0.0, Solid::Below).unwrap();
        let (w, g2) = sample(30, [-14.5; 3], sphere_sdf(10.5));
        let b = marching_cubes(&w, &g2, 0.0, Solid::Below).unwrap();
        let d = surface_distance(&a, &b).unwrap();
        assert!((d.mean - 0.5).abs() < 0.03, "{d:?}");
        assert!((d.rms - 0.5).abs() < 0.03, "{d:?}");
        assert!(d.max < 0.6, "{d:?}");
        let same = surface_distance(&a, &a).unwrap();
        assert!(same.max < 1e-9, "{same:?}");
        assert!(surface_distance(&a, &Mesh::default()).is_none());
    }
}
