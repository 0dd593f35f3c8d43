//! The LLS fit as a glTF 2.0 asset (`docs/pipelines/lls.md`, "Exports"): the sample as a
//! textured quad with the GGX fit in glTF's metallic-roughness material, the registered camera
//! and the check light, for real-time engines, Blender and three.js.
//!
//! glTF's dielectric is not the fitted model: it has a Schlick Fresnel term and takes the
//! diffuse's weight from it (`KHR_materials_specular`: `F·V·D + (1 − max F)·baseColor/π`,
//! `F = F0 + (1 − F0)(1 − |v·h|)⁵`). The mapping matches the fit at normal incidence:
//! `F0 = ρs` (through `specularColorFactor`, which may exceed 1), `baseColor = ρd / (1 − max ρs)`,
//! `roughness = √α`, metallic 0. Away from it the Fresnel term brightens the highlight; the
//! Python test measures by how much under the check light.

use std::path::{Path, PathBuf};

use lightrig_imaging::io::{write_png, BitDepth, Encoding, Image};
use lightrig_pipelines::vec3::V3;
use serde_json::json;

use super::export::{plane_textures, PointLight};
use super::LlsMaps;
use crate::fit::{fail, FitError};

/// glTF's fixed dielectric F0 (IOR 1.5) that `specularColor` scales.
const GLTF_F0: f64 = 0.04;

/// One texel's glTF material from the fit's `ρd`, `ρs`, `α`: linear base colour,
/// `specularColor` (the F0 over 0.04, before the factor that normalises the texture),
/// roughness.
pub fn material(diffuse: [f64; 3], specular: [f64; 3], alpha: f64) -> ([f64; 3], [f64; 3], f64) {
    let f0_max = specular.iter().fold(0.0f64, |a, &s| a.max(s)).clamp(0.0, 0.999);
    let base = diffuse.map(|d| (d / (1.0 - f0_max)).clamp(0.0, 1.0));
    let colour = specular.map(|s| s.clamp(0.0, 1.0) / GLTF_F0);
    (base, colour, alpha.max(0.0).sqrt().min(1.0))
}

/// Our world (millimetres, `z` up) in glTF's (metres, `y` up, right-handed): a quarter turn
/// about `x`.
fn to_gltf(p: V3) -> V3 {
    [p[0] / 1000.0, p[2] / 1000.0, -p[1] / 1000.0]
}

/// The unit quaternion `[x, y, z, w]` of the rotation whose matrix has columns `c`.
pub fn quaternion(c: [V3; 3]) -> [f64; 4] {
    // m[i][j]: row i, column j.
    let m = |i: usize, j: usize| c[j][i];
    let tr = m(0, 0) + m(1, 1) + m(2, 2);
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [(m(2, 1) - m(1, 2)) / s, (m(0, 2) - m(2, 0)) / s, (m(1, 0) - m(0, 1)) / s, s / 4.0]
    } else if m(0, 0) > m(1, 1) && m(0, 0) > m(2, 2) {
        let s = (1.0 + m(0, 0) - m(1, 1) - m(2, 2)).sqrt() * 2.0;
        [s / 4.0, (m(0, 1) + m(1, 0)) / s, (m(0, 2) + m(2, 0)) / s, (m(2, 1) - m(1, 2)) / s]
    } else if m(1, 1) > m(2, 2) {
        let s = (1.0 + m(1, 1) - m(0, 0) - m(2, 2)).sqrt() * 2.0;
        [(m(0, 1) + m(1, 0)) / s, s / 4.0, (m(1, 2) + m(2, 1)) / s, (m(0, 2) - m(2, 0)) / s]
    } else {
        let s = (1.0 + m(2, 2) - m(0, 0) - m(1, 1)).sqrt() * 2.0;
        [(m(0, 2) + m(2, 0)) / s, (m(1, 2) + m(2, 1)) / s, s / 4.0, (m(1, 0) - m(0, 1)) / s]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    // The same rotation either sign; a non-negative w reads better.
    let s = if q[3] < 0.0 { -1.0 / n } else { 1.0 / n };
    q.map(|v| v * s)
}

/// Writes `dir/sample.gltf` with `sample.bin` and its textures (`base_color.png`,
/// `metallic_roughness.png`, `specular_color.png`, and `normal.png` where the session measured
/// normals): the GGX fit on the plane, the registered camera, `light`. Returns the files
/// written.
pub fn write_gltf(m: &LlsMaps, dir: &Path, light: &PointLight) -> Result<Vec<PathBuf>, FitError> {
    let ggx = m.ggx.as_ref().ok_or_else(|| fail("the glTF export needs the GGX fit (`--model both`)"))?;
    let t = plane_textures(m, ggx)?;
    std::fs::create_dir_all(dir).map_err(|e| fail(format!("{}: {e}", dir.display())))?;
    let (tw, th) = (t.width, t.height);
    let n = tw * th;
    // Image row 0 is the plane's largest `y` (the sample seen from above, `y` up), so that the
    // normal map's green channel is `+y`, glTF's "+Y up" convention with the tangents below.
    let texel = |r: usize, c: usize| (th - 1 - r) * tw + c;
    let mats: Vec<_> = (0..n)
        .map(|k| {
            let (d, s, a) =
                (t.diffuse[k].map(f64::from), t.specular[k].map(f64::from), f64::from(t.alpha[k]));
            material(d, s, a)
        })
        .collect();
    // specularColorFactor carries the largest specular colour, so the texture uses its range.
    let peak =
        (0..n).filter(|&k| t.covered[k]).flat_map(|k| mats[k].1).fold(0.0f64, f64::max).max(1.0 / 255.0);
    let (mut base, mut spec, mut mr, mut nrm) =
        (vec![0f32; n * 4], vec![0f32; n * 3], vec![0f32; n * 3], vec![0f32; n * 3]);
    for r in 0..th {
        for c in 0..tw {
            let (k, o) = (texel(r, c), r * tw + c);
            let (b, s, rough) = mats[k];
            for ch in 0..3 {
                base[o * 4 + ch] = b[ch] as f32;
                spec[o * 3 + ch] = (s[ch] / peak) as f32;
                nrm[o * 3 + ch] = (t.normal[k][ch] + 1.0) / 2.0;
            }
            // Uncovered texels are cut out (alphaMode MASK), with a mid roughness.
            base[o * 4 + 3] = if t.covered[k] { 1.0 } else { 0.0 };
            mr[o * 3 + 1] = if t.covered[k] { rough as f32 } else { 0.7 };
        }
    }
    let mut files = Vec::new();
    let mut png = |name: &str, channels: u8, data: Vec<f32>, srgb: bool| -> Result<(), FitError> {
        let img = Image { width: tw as u32, height: th as u32, channels, data, encoding: Encoding::Linear };
        let img = if srgb { img.to_srgb() } else { img };
        let p = dir.join(name);
        // Colours in 8 bits (sRGB), roughness and normals in 16: 1/255 of roughness is 2 % of a
        // small α, where the highlight's peak goes as 1/α².
        let depth = if srgb { BitDepth::Eight } else { BitDepth::Sixteen };
        write_png(&p, &img, depth).map_err(|e| fail(e.to_string()))?;
        files.push(p);
        Ok(())
    };
    png("base_color.png", 4, base, true)?;
    png("specular_color.png", 3, spec, true)?;
    png("metallic_roughness.png", 3, mr, false)?;
    // A session that measured no normals (no stripe, no diagonal passes) gets no normal map:
    // a flat one would read as measured.
    if m.measured.normals {
        png("normal.png", 3, nrm, false)?;
    }

    // The quad: corners at the texture's outer edges, uv (0, 0) at the image's top left, the
    // plane's smallest x and largest y.
    let (x0, y0, x1, y1) = (t.x0, t.y0, t.x0 + tw as f64 * t.texel, t.y0 + th as f64 * t.texel);
    let corners =
        [([x0, y1], [0.0, 0.0]), ([x1, y1], [1.0, 0.0]), ([x0, y0], [0.0, 1.0]), ([x1, y0], [1.0, 1.0])];
    let pos: Vec<V3> = corners.iter().map(|(p, _)| to_gltf([p[0], p[1], t.z])).collect();
    let mut bin = Vec::<u8>::new();
    let mut f32s = |vals: &mut dyn Iterator<Item = f64>| {
        for v in vals {
            bin.extend_from_slice(&(v as f32).to_le_bytes());
        }
    };
    f32s(&mut pos.iter().flatten().copied());
    // Normal +z and tangent +x of our world; w = 1: bitangent = normal × tangent = +y.
    f32s(&mut (0..4).flat_map(|_| to_gltf([0.0, 0.0, 1000.0])));
    f32s(&mut (0..4).flat_map(|_| {
        let [a, b, c] = to_gltf([1000.0, 0.0, 0.0]);
        [a, b, c, 1.0]
    }));
    f32s(&mut corners.iter().flat_map(|(_, uv)| *uv));
    for i in [0u16, 2, 1, 1, 2, 3] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    bin.extend_from_slice(&[0, 0]); // a buffer's length a multiple of 4
    let bin_path = dir.join("sample.bin");
    std::fs::write(&bin_path, &bin).map_err(|e| fail(format!("{}: {e}", bin_path.display())))?;
    files.push(bin_path);
    let lo = (0..3).map(|j| pos.iter().map(|p| p[j]).fold(f64::MAX, f64::min) as f32).collect::<Vec<_>>();
    let hi = (0..3).map(|j| pos.iter().map(|p| p[j]).fold(f64::MIN, f64::max) as f32).collect::<Vec<_>>();

    // The camera: glTF's looks along its −z, +y up, +x right; the pinhole's along +z, y down.
    let r = m.pose.rotation();
    let axis = |j: usize, s: f64| to_gltf([s * r[j][0] * 1000.0, s * r[j][1] * 1000.0, s * r[j][2] * 1000.0]);
    let cam_q = quaternion([axis(0, 1.0), axis(1, -1.0), axis(2, -1.0)]);
    let k = &m.intrinsics;
    let yfov = 2.0 * (f64::from(m.height) / (2.0 * k.fy)).atan();
    let mut uris = vec!["base_color.png", "metallic_roughness.png", "specular_color.png"];
    if m.measured.normals {
        uris.push("normal.png");
    }
    let textures: Vec<_> = (0..uris.len()).map(|i| json!({"sampler": 0, "source": i})).collect();
    let images: Vec<_> = uris.iter().map(|u| json!({"uri": u})).collect();
    let gltf = json!({
        "asset": {
            "version": "2.0",
            "generator": concat!("lightrig ", env!("CARGO_PKG_VERSION"), " (fit lls, GGX)"),
        },
        "extensionsUsed": ["KHR_materials_specular", "KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{
            "type": "point",
            "name": "check light",
            "color": [1.0, 1.0, 1.0],
            // Not photometric: the maps' radiance unit times m², an irradiance of 1 at the sample.
            "intensity": light.intensity * 1e-6,
        }]}},
        "scene": 0,
        "scenes": [{"name": "lls sample", "nodes": [0, 1, 2]}],
        "nodes": [
            {"name": "sample", "mesh": 0},
            {"name": "camera", "camera": 0, "translation": to_gltf(m.pose.camera_centre()), "rotation": cam_q},
            {"name": "check light", "translation": to_gltf(light.position),
             "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"type": "perspective", "name": "registered camera", "perspective": {
            "yfov": yfov,
            "aspectRatio": f64::from(m.width) / f64::from(m.height),
            "znear": 0.001,
            "zfar": 10.0,
        }}],
        "meshes": [{"name": "sample", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
            "indices": 4,
            "material": 0,
        }]}],
        "materials": [{
            "name": "lls GGX fit",
            "pbrMetallicRoughness": {
                "baseColorTexture": {"index": 0},
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
                "metallicRoughnessTexture": {"index": 1},
            },
            "alphaMode": "MASK",
            "alphaCutoff": 0.5,
            "extensions": {"KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularColorFactor": [peak, peak, peak],
                "specularColorTexture": {"index": 2},
            }},
        }],
        "textures": textures,
        "images": images,
        // LINEAR, LINEAR, CLAMP_TO_EDGE.
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
        "buffers": [{"uri": "sample.bin", "byteLength": bin.len()}],
        // One view per attribute: views shared by attributes need a byteStride.
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48, "target": 34962},
            {"buffer": 0, "byteOffset": 48, "byteLength": 48, "target": 34962},
            {"buffer": 0, "byteOffset": 96, "byteLength": 64, "target": 34962},
            {"buffer": 0, "byteOffset": 160, "byteLength": 32, "target": 34962},
            {"buffer": 0, "byteOffset": 192, "byteLength": 12, "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC4"},
            {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 4, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
        "extras": {
            "lightrig": {
                "units": "metres; the sample's plane at the fitted points' median height (not displaced)",
                "texel_mm": t.texel,
                "principal_point_px": [k.cx, k.cy],
                "note": "glTF cameras have no principal point offset or distortion: the view is \
                         centred, fy sets the field of view",
            }
        },
    });
    let mut gltf = gltf;
    if m.measured.normals {
        gltf["materials"][0]["normalTexture"] = json!({"index": 3});
    }
    let p = dir.join("sample.gltf");
    let text = serde_json::to_string_pretty(&gltf).map_err(|e| fail(e.to_string()))?;
    std::fs::write(&p, text).map_err(|e| fail(format!("{}: {e}", p.display())))?;
    files.push(p);
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_material_matches_the_fit_at_normal_incidence() {
        let (base, colour, rough) = material([0.3, 0.2, 0.1], [0.05, 0.1, 0.08], 0.09);
        // F0 = 0.04 · specularColor = ρs; the diffuse's weight 1 − max F0 = 0.9 undone.
        for (c, s) in colour.iter().zip([0.05, 0.1, 0.08]) {
            assert!((c * GLTF_F0 - s).abs() < 1e-12, "{colour:?}");
        }
        for (b, d) in base.iter().zip([0.3, 0.2, 0.1]) {
            assert!((b * 0.9 - d).abs() < 1e-12, "{base:?}");
        }
        assert!((rough - 0.3).abs() < 1e-12);
        // A base colour beyond 1 is clamped, not wrapped.
        assert_eq!(material([0.95, 0.0, 0.0], [0.5; 3], 0.0).0, [1.0, 0.0, 0.0]);
    }

    #[test]
    fn quaternions_of_known_rotations() {
        let close = |a: [f64; 4], b: [f64; 4]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(quaternion([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), [0.0, 0.0, 0.0, 1.0]));
        // A quarter turn about z: x → y, y → −x.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let q = quaternion([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]);
        assert!(close(q, [0.0, 0.0, h, h]), "{q:?}");
        // A half turn about x (trace −1: the branch without w).
        let q = quaternion([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]);
        assert!(close(q, [1.0, 0.0, 0.0, 0.0]), "{q:?}");
        // Our world's z (up) is glTF's y.
        assert_eq!(to_gltf([0.0, 0.0, 1000.0]), [0.0, 1.0, -0.0]);
    }
}
