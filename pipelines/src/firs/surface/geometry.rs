//! Depth map to world points, to a mesh, and several turntable scans into one frame.

use super::{DepthMap, SurfaceError};
use crate::firs::calib::{Aabb, PixelRays, Sheet18};
use crate::firs::mesh::Mesh;
use crate::vec3::{add, cross, dot, norm, scale, sub, V3};

/// Each pixel's surface point: its ray against the sheet at its cut-off time, inside `volume`
/// (row-major, `None` where the depth map, the ray or the intersection is missing).
pub fn depth_to_points(
    depth: &DepthMap,
    rays: &PixelRays,
    sheets: &Sheet18,
    volume: &Aabb,
) -> Result<Vec<Option<V3>>, SurfaceError> {
    if depth.width != rays.width || depth.height != rays.height || depth.t.len() != rays.rays.len() {
        return Err(SurfaceError::Dims(format!(
            "a {}×{} depth map against {}×{} rays",
            depth.width, depth.height, rays.width, rays.height
        )));
    }
    Ok(depth
        .t
        .iter()
        .zip(&rays.rays)
        .map(|(t, r)| sheets.intersect(r.as_ref()?, (*t)?, volume).map(|(_, p)| p))
        .collect())
}

/// A triangle mesh over the pixel grid: per 2×2 block of pixels, the triangles
/// `(u, v), (u, v + 1), (u + 1, v)` and `(u + 1, v), (u, v + 1), (u + 1, v + 1)` whose three
/// points exist and whose edges are all shorter than `max_edge` (longer edges bridge a depth
/// jump, an occluding contour, and are not surface). Vertices are the valid points in pixel
/// order. The triangles wind counter-clockwise in the image (`v` down), which is
/// counter-clockwise seen from the camera: the outside of a scanned surface faces the camera.
pub fn grid_mesh(
    points: &[Option<V3>],
    width: usize,
    height: usize,
    max_edge: f64,
) -> Result<Mesh, SurfaceError> {
    if width.checked_mul(height) != Some(points.len()) {
        return Err(SurfaceError::Dims(format!("{} points for a {width}×{height} grid", points.len())));
    }
    if u32::try_from(points.len()).is_err() {
        return Err(SurfaceError::Dims("more than 2³² points".into()));
    }
    let mut index = vec![u32::MAX; points.len()];
    let mut mesh = Mesh::default();
    for (i, p) in points.iter().enumerate() {
        if let Some(p) = p {
            index[i] = mesh.vertices.len() as u32;
            mesh.vertices.push(*p);
        }
    }
    let short = |a: usize, b: usize| match (points[a], points[b]) {
        (Some(p), Some(q)) => norm(sub(p, q)) < max_edge,
        _ => false,
    };
    for v in 0..height.saturating_sub(1) {
        for u in 0..width.saturating_sub(1) {
            let (a, b, c, d) =
                (v * width + u, (v + 1) * width + u, v * width + u + 1, (v + 1) * width + u + 1);
            for [i, j, k] in [[a, b, c], [c, b, d]] {
                if short(i, j) && short(j, k) && short(k, i) {
                    mesh.triangles.push([index[i], index[j], index[k]]);
                }
            }
        }
    }
    Ok(mesh)
}

/// `p` rotated by `angle` (radians, right-handed) about the axis through `axis_point` along
/// `axis_dir` (Rodrigues' formula; `axis_dir` need not be unit).
pub fn rotate_about_axis(p: V3, axis_point: V3, axis_dir: V3, angle: f64) -> V3 {
    let n = norm(axis_dir);
    if n == 0.0 {
        return p;
    }
    let k = scale(axis_dir, 1.0 / n);
    let r = sub(p, axis_point);
    let (s, c) = angle.sin_cos();
    let rot = add(add(scale(r, c), scale(cross(k, r), s)), scale(k, dot(k, r) * (1.0 - c)));
    add(axis_point, rot)
}

/// Several turntable scans in one frame, the object's at turntable angle 0: scan `k` was taken
/// with the object turned by `scans[k].0` radians (right-handed about `axis_dir` through
/// `axis_point`), so its points are turned back by the negative angle.
pub fn merge_turntable(scans: &[(f64, &[V3])], axis_point: V3, axis_dir: V3) -> Vec<V3> {
    scans
        .iter()
        .flat_map(|(angle, pts)| pts.iter().map(move |p| rotate_about_axis(*p, axis_point, axis_dir, -angle)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_skips_holes_and_jumps() {
        // A 3×3 grid of a plane, the centre-right point lifted by 10 (a jump).
        let (w, h) = (3, 3);
        let mut pts: Vec<Option<V3>> = (0..9).map(|i| Some([(i % 3) as f64, (i / 3) as f64, 0.0])).collect();
        let m = grid_mesh(&pts, w, h, 2.0).unwrap();
        assert_eq!((m.vertices.len(), m.triangles.len()), (9, 8));
        pts[5] = Some([2.0, 1.0, 10.0]);
        // Pixel 5 is in (c, b, d) of the top-right block and both triangles of the bottom-right
        // one: those three go.
        let m = grid_mesh(&pts, w, h, 2.0).unwrap();
        assert_eq!(m.triangles.len(), 5);
        pts[4] = None;
        let m = grid_mesh(&pts, w, h, 2.0).unwrap();
        assert_eq!(m.vertices.len(), 8);
        assert!(m.triangles.iter().all(|t| t.iter().all(|&i| i < 8)));
        assert!(grid_mesh(&pts, 4, 3, 2.0).is_err());
    }

    #[test]
    fn turntable_rotation_round_trip() {
        let (c, a) = ([10.0, 0.0, 5.0], [0.0, 1.0, 0.0]);
        // A quarter turn about +y through c takes c + x̂ to c − ẑ.
        let q = rotate_about_axis([11.0, 0.0, 5.0], c, a, std::f64::consts::FRAC_PI_2);
        assert!(norm(sub(q, [10.0, 0.0, 4.0])) < 1e-12, "{q:?}");
        // An object point seen at 3 turntable angles returns to itself.
        let p = [3.0, 7.0, -2.0];
        let seen: Vec<(f64, Vec<V3>)> =
            [0.3, 2.0, -1.1].iter().map(|&ang| (ang, vec![rotate_about_axis(p, c, a, ang)])).collect();
        let refs: Vec<(f64, &[V3])> = seen.iter().map(|(a, v)| (*a, v.as_slice())).collect();
        for q in merge_turntable(&refs, c, a) {
            assert!(norm(sub(q, p)) < 1e-12);
        }
    }
}
