//! The rig's geometry in the world frame (mm; `z` up along the turntable's axis, the
//! turntable's top at `z = 0`): the turntable's rotation, a calibrated pinhole camera, the
//! galvo laser projector, and which surface point each pixel sees.

use crate::vec3::{add, cross, dot, normalize, scale, sub, V3};

use super::mesh::SurfaceMesh;

/// The object's point `p` (object frame) with the turntable at `deg`: a right-handed turn about
/// the world `z` axis.
pub fn turn(p: V3, deg: f64) -> V3 {
    let (s, c) = deg.to_radians().sin_cos();
    [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]]
}

/// A frame looking from `eye` at `target`: rows are the camera's x (right), y (down) and z
/// (forward) axes in world coordinates; `up` is the world's `+z`.
pub fn look_at(eye: V3, target: V3) -> [V3; 3] {
    let f = normalize(sub(target, eye));
    let mut r = cross(f, [0.0, 0.0, 1.0]);
    if dot(r, r) < 1e-12 {
        r = [1.0, 0.0, 0.0];
    }
    let r = normalize(r);
    let d = cross(f, r);
    [r, d, f]
}

/// A calibrated pinhole camera: square pixels, no distortion (the calibration's undistortion
/// applied before).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub width: u32,
    pub height: u32,
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Principal point, pixels (pixel centres at +0.5).
    pub centre: [f64; 2],
    /// Centre of projection, world mm.
    pub eye: V3,
    /// World → camera rotation (see [`look_at`]).
    pub axes: [V3; 3],
}

impl Pinhole {
    /// A camera at `eye` looking at `target`, principal point at the image centre.
    pub fn looking(width: u32, height: u32, focal_px: f64, eye: V3, target: V3) -> Self {
        Pinhole {
            width,
            height,
            focal_px,
            centre: [f64::from(width) / 2.0, f64::from(height) / 2.0],
            eye,
            axes: look_at(eye, target),
        }
    }

    /// Camera coordinates of world point `p`.
    pub fn to_camera(&self, p: V3) -> V3 {
        let d = sub(p, self.eye);
        [dot(self.axes[0], d), dot(self.axes[1], d), dot(self.axes[2], d)]
    }

    /// The pixel `p` projects to (continuous) and its depth, if in front of the camera.
    pub fn project(&self, p: V3) -> Option<([f64; 2], f64)> {
        let c = self.to_camera(p);
        (c[2] > 1e-9).then(|| {
            (
                [self.centre[0] + self.focal_px * c[0] / c[2], self.centre[1] + self.focal_px * c[1] / c[2]],
                c[2],
            )
        })
    }

    /// The unit ray through continuous pixel position `(x, y)`, world.
    pub fn ray(&self, x: f64, y: f64) -> V3 {
        let u = (x - self.centre[0]) / self.focal_px;
        let v = (y - self.centre[1]) / self.focal_px;
        normalize(add(add(scale(self.axes[0], u), scale(self.axes[1], v)), self.axes[2]))
    }
}

/// The galvo laser projector: the beam leaves the scanner's pivot `eye`; at the galvo's zero
/// codes it points at `target`; code `(x, y)` turns it by `(x − zero)·rad_per_code` about the
/// frame's vertical axis and `(y − zero)·rad_per_code` about its horizontal one (optical angles).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projector {
    pub eye: V3,
    pub axes: [V3; 3],
    /// Zero codes `[x, y]`.
    pub zero: [f64; 2],
    /// Optical radians per code `[x, y]` (signed: a mirrored axis is negative).
    pub rad_per_code: [f64; 2],
}

impl Projector {
    /// The projector at `eye` aimed at `target` at its zero codes.
    pub fn aimed(eye: V3, target: V3, zero: [f64; 2], rad_per_code: [f64; 2]) -> Self {
        Projector { eye, axes: look_at(eye, target), zero, rad_per_code }
    }

    /// The beam's unit direction at galvo code `code`, world.
    pub fn ray(&self, code: [f64; 2]) -> V3 {
        let ax = (code[0] - self.zero[0]) * self.rad_per_code[0];
        let ay = (code[1] - self.zero[1]) * self.rad_per_code[1];
        normalize(add(add(scale(self.axes[0], ax.tan()), scale(self.axes[1], ay.tan())), self.axes[2]))
    }

    /// The code that points the beam at world point `p` (inverse of [`Projector::ray`]).
    pub fn code_of(&self, p: V3) -> [f64; 2] {
        let d = sub(p, self.eye);
        let c = [dot(self.axes[0], d), dot(self.axes[1], d), dot(self.axes[2], d)];
        [
            self.zero[0] + (c[0] / c[2]).atan() / self.rad_per_code[0],
            self.zero[1] + (c[1] / c[2]).atan() / self.rad_per_code[1],
        ]
    }
}

/// Where a ray meets the surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Triangle index.
    pub triangle: u32,
    /// Barycentric weights of its three vertices.
    pub bary: [f32; 3],
    /// Distance along the ray, mm.
    pub t: f32,
}

/// Möller–Trumbore: the distance along unit ray `(o, d)` to triangle `(a, b, c)` and the
/// barycentric weights of `b` and `c`, if it hits in front.
pub fn ray_triangle(o: V3, d: V3, a: V3, b: V3, c: V3) -> Option<(f64, f64, f64)> {
    let e1 = sub(b, a);
    let e2 = sub(c, a);
    let p = cross(d, e2);
    let det = dot(e1, p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let s = sub(o, a);
    let u = dot(s, p) * inv;
    if !(-1e-9..=1.0 + 1e-9).contains(&u) {
        return None;
    }
    let q = cross(s, e1);
    let v = dot(d, q) * inv;
    if v < -1e-9 || u + v > 1.0 + 1e-9 {
        return None;
    }
    let t = dot(e2, q) * inv;
    (t > 1e-9).then_some((t, u, v))
}

/// The object's vertices with the turntable at `deg`, world.
pub fn turned(mesh: &SurfaceMesh, deg: f64) -> Vec<V3> {
    mesh.vertices.iter().map(|&v| turn(v, deg)).collect()
}

/// The nearest hit of ray `(o, d)` on the surface with vertices `world`, brute force (a beam, a
/// handful of rays per frame).
pub fn cast(mesh: &SurfaceMesh, world: &[V3], o: V3, d: V3) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    for (k, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|i| world[i as usize]);
        if let Some((dist, u, v)) = ray_triangle(o, d, a, b, c) {
            if best.is_none_or(|h| dist < f64::from(h.t)) {
                best = Some(Hit {
                    triangle: k as u32,
                    bary: [(1.0 - u - v) as f32, u as f32, v as f32],
                    t: dist as f32,
                });
            }
        }
    }
    best
}

/// For every pixel centre (row-major), the surface point it sees: each triangle's ray tests
/// over the pixels of its projected bounding box, the nearest kept (a z-buffer with exact
/// ray–triangle distances).
pub fn surface_map(mesh: &SurfaceMesh, world: &[V3], cam: &Pinhole) -> Vec<Option<Hit>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut map: Vec<Option<Hit>> = vec![None; w * h];
    for (k, tri) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = tri.map(|i| world[i as usize]);
        let (Some((pa, _)), Some((pb, _)), Some((pc, _))) = (cam.project(a), cam.project(b), cam.project(c))
        else {
            continue;
        };
        let x0 = (pa[0].min(pb[0]).min(pc[0]) - 0.5).floor().max(0.0) as usize;
        let y0 = (pa[1].min(pb[1]).min(pc[1]) - 0.5).floor().max(0.0) as usize;
        let x1 = ((pa[0].max(pb[0]).max(pc[0]) + 0.5).ceil() as usize).min(w);
        let y1 = ((pa[1].max(pb[1]).max(pc[1]) + 0.5).ceil() as usize).min(h);
        for y in y0..y1 {
            for x in x0..x1 {
                let d = cam.ray(x as f64 + 0.5, y as f64 + 0.5);
                if let Some((t, u, v)) = ray_triangle(cam.eye, d, a, b, c) {
                    let slot = &mut map[y * w + x];
                    if slot.is_none_or(|h| t < f64::from(h.t)) {
                        *slot = Some(Hit {
                            triangle: k as u32,
                            bary: [(1.0 - u - v) as f32, u as f32, v as f32],
                            t: t as f32,
                        });
                    }
                }
            }
        }
    }
    map
}

/// Per-vertex values `at` (points, normals) mixed by `hit`'s barycentric weights.
pub fn at_hit(mesh: &SurfaceMesh, at: &[V3], hit: &Hit) -> V3 {
    let tri = mesh.triangles[hit.triangle as usize];
    (0..3).fold([0.0; 3], |acc, k| add(acc, scale(at[tri[k] as usize], f64::from(hit.bary[k]))))
}

/// The world point and interpolated unit normal of `hit` (normals turned with the object).
pub fn point_of(mesh: &SurfaceMesh, world: &[V3], deg: f64, hit: &Hit) -> (V3, V3) {
    (at_hit(mesh, world, hit), normalize(turn(at_hit(mesh, &mesh.normals, hit), deg)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disco::mesh::{pebble, SurfaceMesh};
    use crate::vec3::norm;

    #[test]
    fn projection_and_rays_are_inverse() {
        let cam = Pinhole::looking(320, 200, 400.0, [200.0, -50.0, 60.0], [0.0, 0.0, 30.0]);
        let p = [5.0, -3.0, 40.0];
        let (px, depth) = cam.project(p).unwrap();
        let back = add(cam.eye, scale(cam.ray(px[0], px[1]), norm(sub(p, cam.eye))));
        assert!(norm(sub(back, p)) < 1e-9);
        assert!(depth > 0.0);
        // The target is at the image centre; +z in the world is up in the image.
        let (c, _) = cam.project([0.0, 0.0, 30.0]).unwrap();
        assert!((c[0] - 160.0).abs() < 1e-9 && (c[1] - 100.0).abs() < 1e-9);
        assert!(cam.project([0.0, 0.0, 40.0]).unwrap().0[1] < 100.0);
    }

    #[test]
    fn projector_codes_round_trip_and_the_surface_map_sees_the_front() {
        let proj = Projector::aimed([250.0, 0.0, 40.0], [0.0, 0.0, 30.0], [32768.0, 32768.0], [1e-5, -1e-5]);
        let p = [3.0, 7.0, 25.0];
        let code = proj.code_of(p);
        let d = proj.ray(code);
        let along = sub(p, proj.eye);
        assert!(norm(cross(d, normalize(along))) < 1e-12);
        let mesh = SurfaceMesh::new(&pebble(2, [20.0, 20.0, 30.0]));
        let world = turned(&mesh, 30.0);
        let cam = Pinhole::looking(160, 100, 200.0, [200.0, 0.0, 30.0], [0.0, 0.0, 30.0]);
        let map = surface_map(&mesh, &world, &cam);
        let centre = map[50 * 160 + 80].expect("the object fills the centre");
        let (pt, n) = point_of(&mesh, &world, 30.0, &centre);
        // The camera on +x sees the pebble's +x side, facing it.
        assert!(pt[0] > 15.0 && n[0] > 0.9, "{pt:?} {n:?}");
        assert!(map[0].is_none());
        // A cast from the camera through that pixel finds the same point.
        let h = cast(&mesh, &world, cam.eye, cam.ray(80.5, 50.5)).unwrap();
        assert_eq!(h.triangle, centre.triangle);
    }
}
