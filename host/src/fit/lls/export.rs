//! The LLS fit for renderers: the maps resampled from the camera's pixels onto the sample
//! plane as textures, and a Mitsuba 3 scene that renders the GGX fit with them from the
//! registered camera under a point light (`docs/pipelines/lls.md`, "Exports").
//!
//! Conventions (the table in the docs): textures are linear, row 0 at the plane's smallest
//! `y`, column 0 at its smallest `x`; normals are world (= the plane's tangent frame: `x`, `y`,
//! up) stored as `(n + 1)/2`; lengths are millimetres. Mitsuba has no sum of two BSDFs, so the
//! scene takes `blendbsdf` at weight ½ of a `diffuse` of reflectance `2ρd` and a
//! `roughconductor` (GGX, no Fresnel: `material = "none"`) of reflectance `2ρs`: exactly
//! `ρd/π + ρs·f_GGX`.

use std::path::{Path, PathBuf};

use lightrig_imaging::calib::project;
use lightrig_imaging::io::{write_exr, Encoding, ExrPrecision, Image};
use lightrig_pipelines::ggx::Ggx;
use lightrig_pipelines::lls::TraceFit;
use lightrig_pipelines::vec3::{dot, normalize, sub, V3};
use lightrig_pipelines::ward::Ward;

use super::LlsMaps;
use crate::fit::{fail, FitError};

/// An isotropic point light: `intensity` in the maps' radiance units times mm².
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointLight {
    /// Position, mm.
    pub position: V3,
    /// Radiant intensity per colour channel.
    pub intensity: f64,
}

/// Which fitted model a relit image uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    Ward,
    Ggx,
}

/// The light of the exports and of the relit images: above the sample at 120 mm, where the
/// camera sees its mirror highlight at the middle of the fitted pixels (a light no frame of
/// the session used: a point, not the tube), its intensity giving an irradiance of 1 there.
pub fn check_light(m: &LlsMaps) -> PointLight {
    let pts: Vec<V3> = (0..m.fitted.len()).filter(|&i| m.fitted[i]).filter_map(|i| m.points[i]).collect();
    let n = pts.len().max(1) as f64;
    let centre = pts.iter().fold([0.0; 3], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]);
    let v = sub(m.pose.camera_centre(), centre);
    let height = 120.0;
    let t = height / v[2].max(1e-9);
    let position = [centre[0] - v[0] * t, centre[1] - v[1] * t, centre[2] + height];
    let d2 = dot(sub(position, centre), sub(position, centre));
    PointLight { position, intensity: d2 / (height / d2.sqrt()) }
}

/// The fitted pixels relit by `light` with `model`'s fit, as the camera sees them: interleaved
/// RGB radiance, zero where nothing was fitted (or the GGX fit was not made: `None`).
pub fn relit(m: &LlsMaps, model: Model, light: &PointLight) -> Option<Vec<f32>> {
    let fits = match model {
        Model::Ward => &m.fit,
        Model::Ggx => m.ggx.as_ref()?,
    };
    let eye = m.pose.camera_centre();
    let mut out = vec![0f32; m.fitted.len() * 3];
    for i in 0..m.fitted.len() {
        let (true, Some(p), Some(n)) = (m.fitted[i], m.points[i], m.normals[i]) else { continue };
        let f = &fits[i];
        let to = sub(light.position, p);
        let d2 = dot(to, to);
        let (wi, wo) = (normalize(to), normalize(sub(eye, p)));
        let brdf = match model {
            Model::Ward => {
                Ward { diffuse: f.diffuse, specular: f.specular, alpha: f.alpha.max(1e-3) }.eval(n, wi, wo)
            }
            Model::Ggx => {
                Ggx { diffuse: f.diffuse, specular: f.specular, alpha: f.alpha.max(1e-3) }.eval(n, wi, wo)
            }
        };
        let e = light.intensity * dot(n, wi).max(0.0) / d2;
        for c in 0..3 {
            out[i * 3 + c] = (brdf[c] * e) as f32;
        }
    }
    Some(out)
}

/// The fit resampled onto a grid of the plane `z = height`, row 0 at `y0`, column 0 at `x0`.
#[derive(Debug, Clone)]
pub struct PlaneTextures {
    pub width: usize,
    pub height: usize,
    /// Corner of texel (0, 0), mm (its outer corner, not its centre).
    pub x0: f64,
    pub y0: f64,
    /// Texel size, mm: the pixels' median footprint.
    pub texel: f64,
    /// The plane's height, mm: the fitted points' median.
    pub z: f64,
    pub diffuse: Vec<[f32; 3]>,
    pub specular: Vec<[f32; 3]>,
    pub alpha: Vec<f32>,
    pub normal: Vec<[f32; 3]>,
    /// Texels some fitted pixel sees.
    pub covered: Vec<bool>,
}

/// `fits` (one per pixel of `m`) and `m`'s normals on the plane: each texel's centre
/// projected into the camera (at the height of the pixel it lands on), bilinear between the
/// four pixels around it where all are fitted, else the nearest pixel where that is.
pub fn plane_textures(m: &LlsMaps, fits: &[TraceFit]) -> Result<PlaneTextures, FitError> {
    let (w, h) = (m.width as usize, m.height as usize);
    let on = |x: usize, y: usize| -> Option<usize> {
        let i = y * w + x;
        (m.fitted[i] && m.points[i].is_some() && m.normals[i].is_some()).then_some(i)
    };
    let mut xs = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    let (mut steps, mut heights) = (Vec::new(), Vec::new());
    for y in 0..h {
        for x in 0..w {
            let Some(i) = on(x, y) else { continue };
            let p = m.points[i].unwrap_or_default();
            xs = (xs.0.min(p[0]), xs.1.max(p[0]), xs.2.min(p[1]), xs.3.max(p[1]));
            heights.push(p[2]);
            if let Some(j) = (x + 1 < w).then(|| on(x + 1, y)).flatten() {
                let q = m.points[j].unwrap_or_default();
                steps.push((q[0] - p[0]).hypot(q[1] - p[1]));
            }
        }
    }
    if steps.is_empty() {
        return Err(fail("no two neighbouring pixels were fitted: nothing to export"));
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (texel, z) = (median(&mut steps), median(&mut heights));
    let (tw, th) = (((xs.1 - xs.0) / texel).ceil() as usize + 1, ((xs.3 - xs.2) / texel).ceil() as usize + 1);
    let (x0, y0) = (xs.0 - texel / 2.0, xs.2 - texel / 2.0);
    let mut t = PlaneTextures {
        width: tw,
        height: th,
        x0,
        y0,
        texel,
        z,
        diffuse: vec![[0.0; 3]; tw * th],
        specular: vec![[0.0; 3]; tw * th],
        alpha: vec![0.0; tw * th],
        normal: vec![[0.0, 0.0, 1.0]; tw * th],
        covered: vec![false; tw * th],
    };
    let px = |p: V3| project(&m.intrinsics, &m.pose, p);
    for r in 0..th {
        for c in 0..tw {
            let (x, y) = (x0 + (c as f64 + 0.5) * texel, y0 + (r as f64 + 0.5) * texel);
            // At the plane's height first, then at the height of the pixel that lands on.
            let Some((u, v)) = px([x, y, z]) else { continue };
            let near = |u: f64, v: f64| {
                let (a, b) = (u.round(), v.round());
                (a >= 0.0 && b >= 0.0 && (a as usize) < w && (b as usize) < h)
                    .then(|| on(a as usize, b as usize))
                    .flatten()
            };
            let Some(first) = near(u, v) else { continue };
            let zh = m.points[first].map_or(z, |p| p[2]);
            let Some((u, v)) = px([x, y, zh]) else { continue };
            let (fu, fv) = (u.floor(), v.floor());
            let corners =
                (fu >= 0.0 && fv >= 0.0 && (fu as usize) + 1 < w && (fv as usize) + 1 < h).then(|| {
                    let (a, b) = (fu as usize, fv as usize);
                    [(a, b), (a + 1, b), (a, b + 1), (a + 1, b + 1)].map(|(x, y)| on(x, y))
                });
            let (du, dv) = (u - fu, v - fv);
            let weighted: Vec<(usize, f64)> = match corners {
                Some([Some(a), Some(b), Some(c2), Some(d)]) => vec![
                    (a, (1.0 - du) * (1.0 - dv)),
                    (b, du * (1.0 - dv)),
                    (c2, (1.0 - du) * dv),
                    (d, du * dv),
                ],
                _ => match near(u, v) {
                    Some(i) => vec![(i, 1.0)],
                    None => continue,
                },
            };
            let k = r * tw + c;
            let (mut rd, mut rs, mut al, mut n) = ([0.0; 3], [0.0; 3], 0.0, [0.0; 3]);
            for &(i, wgt) in &weighted {
                let f = &fits[i];
                let ni = m.normals[i].unwrap_or([0.0, 0.0, 1.0]);
                for ch in 0..3 {
                    rd[ch] += wgt * f.diffuse[ch];
                    rs[ch] += wgt * f.specular[ch];
                    n[ch] += wgt * ni[ch];
                }
                al += wgt * f.alpha;
            }
            t.diffuse[k] = rd.map(|v| v as f32);
            t.specular[k] = rs.map(|v| v as f32);
            t.alpha[k] = al as f32;
            t.normal[k] = normalize(n).map(|v| v as f32);
            t.covered[k] = true;
        }
    }
    Ok(t)
}

/// Writes `dir/scene.xml` and its textures (`diffuse.exr`, `specular.exr`, `alpha.exr`, and
/// `normal.exr` where the session measured normals): the GGX fit on the plane, the registered camera (pinhole: `fx` sets the
/// field of view, `cx`, `cy` the principal point; distortion is not rendered), `light`.
/// Returns the files written.
pub fn write_mitsuba(m: &LlsMaps, dir: &Path, light: &PointLight) -> Result<Vec<PathBuf>, FitError> {
    let ggx = m.ggx.as_ref().ok_or_else(|| fail("the Mitsuba export needs the GGX fit (`--model both`)"))?;
    let t = plane_textures(m, ggx)?;
    std::fs::create_dir_all(dir).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let (tw, th) = (t.width as u32, t.height as u32);
    let mut files = Vec::new();
    let mut exr = |name: &str, channels: u8, data: Vec<f32>| -> Result<(), FitError> {
        let img = Image { width: tw, height: th, channels, data, encoding: Encoding::Linear };
        let p = dir.join(name);
        write_exr(&p, &img, ExrPrecision::Float).map_err(|e| fail(e.to_string()))?;
        files.push(p);
        Ok(())
    };
    // Uncovered texels: black, and a mid roughness (a zero α is a mirror).
    exr("diffuse.exr", 3, t.diffuse.iter().flat_map(|v| v.map(|x| 2.0 * x)).collect())?;
    exr("specular.exr", 3, t.specular.iter().flat_map(|v| v.map(|x| 2.0 * x)).collect())?;
    exr(
        "alpha.exr",
        1,
        t.alpha.iter().zip(&t.covered).map(|(&a, &c)| if c { a.max(1e-3) } else { 0.5 }).collect(),
    )?;
    // A session that measured no normals (no stripe, no diagonal passes) gets no normal map:
    // a flat one would read as measured.
    if m.measured.normals {
        exr("normal.exr", 3, t.normal.iter().flat_map(|v| v.map(|x| (x + 1.0) / 2.0)).collect())?;
    }
    let k = &m.intrinsics;
    let (w, h) = (f64::from(m.width), f64::from(m.height));
    let fov = (2.0 * (w / (2.0 * k.fx)).atan()).to_degrees();
    // Mitsuba's camera looks along its +z with +y up and +x left: the columns of its
    // to-world matrix are the pinhole's −x, −y, +z in the world, and the camera centre.
    let r = m.pose.rotation();
    let c = m.pose.camera_centre();
    let col = |j: usize, s: f64| [s * r[j][0], s * r[j][1], s * r[j][2]];
    let (ax, ay, az) = (col(0, -1.0), col(1, -1.0), col(2, 1.0));
    let matrix = format!(
        "{} {} {} {} {} {} {} {} {} {} {} {} 0 0 0 1",
        ax[0], ay[0], az[0], c[0], ax[1], ay[1], az[1], c[1], ax[2], ay[2], az[2], c[2]
    );
    let (hx, hy) = (t.width as f64 * t.texel / 2.0, t.height as f64 * t.texel / 2.0);
    let (mx, my) = (t.x0 + hx, t.y0 + hy);
    let [lx, ly, lz] = light.position;
    let skew = if (k.fx / k.fy - 1.0).abs() > 1e-3 {
        format!(
            "\n     fy = {} differs from fx: Mitsuba's pinhole has square pixels, the image is fx's.",
            k.fy
        )
    } else {
        String::new()
    };
    // The blend of the diffuse and GGX lobes, in a normal map where the session measured
    // normals.
    let blend = r#"      <bsdf type="blendbsdf">
        <float name="weight" value="0.5"/>
        <bsdf type="diffuse">
          <texture name="reflectance" type="bitmap">
            <string name="filename" value="diffuse.exr"/>
            <boolean name="raw" value="true"/>
          </texture>
        </bsdf>
        <bsdf type="roughconductor">
          <string name="material" value="none"/>
          <string name="distribution" value="ggx"/>
          <boolean name="sample_visible" value="true"/>
          <texture name="alpha" type="bitmap">
            <string name="filename" value="alpha.exr"/>
            <boolean name="raw" value="true"/>
          </texture>
          <texture name="specular_reflectance" type="bitmap">
            <string name="filename" value="specular.exr"/>
            <boolean name="raw" value="true"/>
          </texture>
        </bsdf>
      </bsdf>"#;
    let bsdf = if m.measured.normals {
        format!(
            r#"    <bsdf type="normalmap">
      <texture name="normalmap" type="bitmap">
        <string name="filename" value="normal.exr"/>
        <boolean name="raw" value="true"/>
      </texture>
{blend}
    </bsdf>"#
        )
    } else {
        let lines: Vec<&str> = blend.lines().map(|l| l.strip_prefix("  ").unwrap_or(l)).collect();
        format!(
            "    <!-- No normal map: the session measured no normals (no stripe, no diagonal passes). -->\n{}",
            lines.join("\n")
        )
    };
    let xml = format!(
        r#"<?xml version="1.0" encoding="utf-8"?>
<!-- lightrig fit lls: the GGX fit of the sample as a textured plane, seen by the registered
     camera ({width} x {height} px, fx = {fx}, cx = {cx}, cy = {cy}; distortion not rendered), lit by a
     point light no frame used. Millimetres. Render with `mitsuba scene.xml` (variant scalar_rgb).
     f = 0.5 * diffuse(2 rho_d) + 0.5 * roughconductor(GGX, 2 rho_s, no Fresnel) = rho_d/pi + rho_s f_GGX.{skew} -->
<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="{fov}"/>
    <string name="fov_axis" value="x"/>
    <float name="principal_point_offset_x" value="{ppx}"/>
    <float name="principal_point_offset_y" value="{ppy}"/>
    <float name="near_clip" value="1"/>
    <float name="far_clip" value="10000"/>
    <transform name="to_world"><matrix value="{matrix}"/></transform>
    <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="{width}"/>
      <integer name="height" value="{height}"/>
      <string name="pixel_format" value="rgb"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <shape type="rectangle">
    <!-- {tw} x {th} texels of {texel} mm from ({x0}, {y0}), at the fitted points' median height. -->
    <transform name="to_world">
      <scale x="{hx}" y="{hy}" z="1"/>
      <translate x="{mx}" y="{my}" z="{z}"/>
    </transform>
{bsdf}
  </shape>
  <emitter type="point">
    <point name="position" x="{lx}" y="{ly}" z="{lz}"/>
    <rgb name="intensity" value="{i}, {i}, {i}"/>
  </emitter>
</scene>
"#,
        width = m.width,
        height = m.height,
        fx = k.fx,
        cx = k.cx,
        cy = k.cy,
        ppx = ((w - 1.0) / 2.0 - k.cx) / w,
        ppy = ((h - 1.0) / 2.0 - k.cy) / h,
        texel = t.texel,
        x0 = t.x0,
        y0 = t.y0,
        z = t.z,
        i = light.intensity,
    );
    let p = dir.join("scene.xml");
    std::fs::write(&p, xml).map_err(|e| fail(format!("{}: {e}", p.display())))?;
    files.push(p);
    Ok(files)
}
