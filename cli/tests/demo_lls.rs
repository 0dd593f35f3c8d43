//! The virtual rig end to end: the linear-light-source demo at quick size, its fit checked
//! against the ground truth the frames were rendered from, and the virtual camera's renders
//! checked against closed forms and for determinism.

use lightrig_cli::demo::lls::{run_lls, DemoOptions};
use lightrig_sim::camera::{RigState, Scene};
use lightrig_sim::scenes::lls::{LlsScene, LlsSceneSpec, Region};
use lightrig_sim::sensor::Sensor;

#[test]
fn lls_demo_meets_the_accuracy_targets() {
    let out = std::env::temp_dir().join(format!("lightrig-demo-test-{}", std::process::id()));
    let opts = DemoOptions {
        quick: true,
        out: out.clone(),
        seed: 7,
        progress: false,
        real_time: false,
        step_mm: None,
        camera_gamma: None,
    };
    let (acc, report) = run_lls(&opts).unwrap();
    assert!(acc.pixels > 1500, "{} pixels compared", acc.pixels);
    for (name, value, limit, met) in acc.targets() {
        assert!(met, "{name}: {value} > {limit}");
    }
    assert!(acc.translucency_abs < 0.01, "translucency {}", acc.translucency_abs);
    let text = std::fs::read_to_string(report).unwrap();
    assert!(text.contains("| roughness, median rel |"), "{text}");
    for f in [
        "fit/maps.exr",
        "fit/relit.png",
        "truth/truth.exr",
        "truth/scene.json",
        "rig.toml",
        "session/journal.jsonl",
        "truth/point-light.exr",
        "fit/relit-point.exr",
        "fit/relight.png",
        "fit/mitsuba/scene.xml",
        "fit/mitsuba/diffuse.exr",
        "fit/mitsuba/specular.exr",
        "fit/mitsuba/alpha.exr",
        "fit/mitsuba/normal.exr",
        "fit/gltf/sample.gltf",
        "fit/gltf/sample.bin",
        "fit/gltf/base_color.png",
        "fit/gltf/metallic_roughness.png",
        "fit/gltf/normal.png",
        "fit/gltf/specular_color.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // Under the check light (a point no frame used), each model's image of the sample against
    // the true sample's: the report's rows `| model | pixels | median | 95th percentile |`.
    // Measured on the quick demo: Ward 1.09 % / 6.1 %, GGX (fitted to Ward materials) 4.7 % /
    // 18.4 %.
    let relit = |model: &str| -> (f64, f64) {
        let row = text
            .lines()
            .find(|l| l.starts_with(&format!("| {model} | ")))
            .unwrap_or_else(|| panic!("{text}"));
        let cells: Vec<f64> = row.split('|').filter_map(|c| c.trim().parse().ok()).collect();
        (cells[1], cells[2])
    };
    let (ward, ggx) = (relit("Ward"), relit("GGX"));
    assert!(ward.0 < 0.02 && ward.1 < 0.1, "Ward under the check light: {ward:?}");
    assert!(ggx.0 < 0.06 && ggx.1 < 0.25, "GGX under the check light: {ggx:?}");
    assert!(text.contains("| true Ward α | pixels | Ward residual | GGX residual | GGX α |"), "{text}");
    assert!(text.contains("![truth, GGX fit, 10 × |error| under the check light](fit/relight.png)"));
    // The session is an ordinary one: `lightrig fit lls` reads it again to the same maps
    // (every number of the comparison with the truth agrees).
    let again = lightrig_host::fit::lls::fit_session(
        &out.join("session"),
        Some(&out.join("camera.toml")),
        &out.join("again"),
        &|_, _| {},
    )
    .unwrap();
    let scene = LlsScene::new(LlsSceneSpec::new(80, 60));
    assert_eq!(lightrig_cli::demo::lls::lls_accuracy(&scene, &again, 2.0), acc);
    fit_checks_agree_with_the_truth(&out, &again, &scene);
    the_figures_show_the_maps(&out, &again, &scene);
    // Streamed in small blocks (a tenth of the quick session's traces at most resident) the
    // fit gives exactly the same maps as with all of them in one block.
    let small = 1 << 20;
    let streamed = lightrig_host::fit::lls::fit_session_with(
        &out.join("session"),
        Some(&out.join("camera.toml")),
        lightrig_host::fit::lls::Streaming {
            scratch: &out.join("streamed"),
            block_bytes: small,
            tables: Some(&out.join("tables.bin")),
        },
        None,
        &|_, _| {},
    )
    .unwrap();
    // It kept the lobe tables it built; a fit that reads them gives the same maps.
    assert!(streamed.tables_note.contains("none kept") && streamed.tables_note.contains("now kept"));
    let from_kept = lightrig_host::fit::lls::fit_session_with(
        &out.join("session"),
        Some(&out.join("camera.toml")),
        lightrig_host::fit::lls::Streaming {
            scratch: &out.join("streamed"),
            block_bytes: lightrig_host::fit::lls::BLOCK_BYTES,
            tables: Some(&out.join("tables.bin")),
        },
        Some(lightrig_host::fit::lls::Models::Ward),
        &|_, _| {},
    )
    .unwrap();
    assert!(from_kept.tables_note.contains("nodes read from"), "{}", from_kept.tables_note);
    assert!(!from_kept.tables_note.contains("now kept"), "{}", from_kept.tables_note);
    assert_same_maps(&from_kept, &again);
    assert!(again.resident_trace_bytes > 10 * small, "{} bytes in one block", again.resident_trace_bytes);
    assert!(streamed.resident_trace_bytes <= small, "{} bytes resident", streamed.resident_trace_bytes);
    assert_same_maps(&streamed, &again);
    assert!(std::fs::read_dir(out.join("streamed")).unwrap().next().is_none(), "scratch files left");
    // The diagonal passes were used, and their normals alone meet the target too.
    assert_eq!(again.diagonal_mounts, vec![-15, 15]);
    assert!(acc.photometric_normal_deg < 1.0, "{}", acc.photometric_normal_deg);
    // Both blends are reported; the frequency split is the default and what the fit used, the
    // paper's ρs/α blend meets the target too.
    let report_text = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report_text.contains("| normal, frequency split of the two (used), median deg |"),
        "{report_text}"
    );
    assert!(report_text.contains("| normal, blended by ρs/α as the paper's §7.2, median deg |"));
    assert_eq!(acc.split_normal_deg, acc.normal_deg);
    assert!(acc.gloss_normal_deg < 1.0, "{}", acc.gloss_normal_deg);
    // `[plan.fit] normal_blend = "gloss"` makes the fit use the paper's blend: the same session
    // with that line in its rig file.
    let gloss_session = out.join("gloss-session");
    copy_dir(&out.join("session"), &gloss_session);
    let manifest = gloss_session.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    let rig = m["rig"].as_str().unwrap().replace("[plan.fit]\n", "[plan.fit]\nnormal_blend = \"gloss\"\n");
    m["rig"] = rig.into();
    std::fs::write(&manifest, serde_json::to_string_pretty(&m).unwrap()).unwrap();
    let gloss = lightrig_host::fit::lls::fit_session(
        &gloss_session,
        Some(&out.join("camera.toml")),
        &out.join("gloss"),
        &|_, _| {},
    )
    .unwrap();
    assert_eq!(gloss.normal_blend, lightrig_host::fit::lls::NormalBlend::Gloss);
    assert_eq!(gloss.gloss_normals, again.gloss_normals, "the blends do not depend on the choice");
    for i in (0..gloss.normals.len()).filter(|&i| gloss.fitted[i]) {
        assert_eq!(gloss.normals[i], gloss.gloss_normals[i]);
    }
    // The check frame (relit.png's pair): the maps' prediction of the middle frame against the
    // capture, over the fitted pixels, relative to the capture's median there.
    let (_, captured, predicted) = &again.check_frame;
    let median = |mut v: Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    let fitted = |j: &usize| again.fitted[j / 3];
    let level = median((0..captured.len()).filter(fitted).map(|j| captured[j]).collect());
    let off =
        median((0..captured.len()).filter(fitted).map(|j| (captured[j] - predicted[j]).abs()).collect());
    // Measured 6.2 % (the frame's noise: one frame, where the fit saw the whole trace).
    assert!(level > 0.0 && off < 0.08 * level, "check frame: {off} off a median level of {level}");
    std::fs::remove_dir_all(&out).ok();
}

/// The fit's masks and checks (`maps.exr` layers `valid.*`, `quality.json`) against the scene the
/// frames were rendered from, and a session without its stripe and backlit passes: the maps it
/// cannot measure are not written, and the checks say so.
fn fit_checks_agree_with_the_truth(
    out: &std::path::Path,
    m: &lightrig_host::fit::lls::LlsMaps,
    scene: &LlsScene,
) {
    use lightrig_host::fit::lls::{quality, write_outputs};
    let valid = quality::validity(m);
    // The share of the fitted pixels of a region where a mask holds.
    let share = |region: Region, mask: &[bool]| {
        let px: Vec<usize> =
            (0..mask.len()).filter(|&i| scene.truth[i].region == region && m.fitted[i]).collect();
        (px.iter().filter(|&&i| mask[i]).count() as f64 / px.len().max(1) as f64, px.len())
    };
    // Every tile is glossy (ρs 0.05–0.15): α determined nearly everywhere on the sample.
    let (rough, n) = share(Region::Sample, &valid.roughness);
    assert!(n > 1500 && rough > 0.9, "α determined on {:.1} % of {n} sample pixels", 100.0 * rough);
    let (height, _) = share(Region::Sample, &valid.height);
    assert!(height > 0.9, "height from the stripe on {:.1} % of the sample", 100.0 * height);
    let (physical, _) = share(Region::Sample, &valid.physical);
    assert_eq!(physical, 1.0);
    // Where α is said to be determined it is within 10 % of the truth on 95 % of the pixels;
    // where it is not, the error is larger (what the mask is for).
    let rel = |i: usize| (m.fit[i].alpha / scene.truth[i].material.alpha - 1.0).abs();
    let on_sample = |i: &usize| scene.truth[*i].region == Region::Sample && m.fitted[*i];
    let good: Vec<f64> =
        (0..valid.roughness.len()).filter(on_sample).filter(|&i| valid.roughness[i]).map(rel).collect();
    let within = good.iter().filter(|&&e| e < 0.1).count() as f64 / good.len() as f64;
    assert!(within > 0.95, "{:.1} % of the determined α within 10 %", 100.0 * within);
    // quality.json is the same assessment.
    let q: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit/quality.json")).unwrap()).unwrap();
    let expected = quality::assess(m, &valid);
    assert_eq!(q["fitted"]["pixels"], expected.fitted.pixels);
    assert_eq!(q["fitted"]["pixels"], valid.reflectance.iter().filter(|&&v| v).count());
    assert_eq!(q["roughness_determined"]["pixels"], expected.roughness_determined.pixels);
    assert_eq!(q["unmeasured"], serde_json::json!([]));
    // The camera of the maps' pixel grid as documented (world → camera, a point X at R·X + t):
    // the board frame's pose puts the camera where the scene's is.
    let (k, pose) = scene.spec.camera.model();
    assert_eq!((q["camera"]["fx"].as_f64(), q["camera"]["cx"].as_f64()), (Some(k.fx), Some(k.cx)));
    let v3 = |v: &serde_json::Value| -> [f64; 3] { std::array::from_fn(|j| v[j].as_f64().unwrap()) };
    let fitted_pose =
        lightrig_imaging::calib::Pose { rvec: v3(&q["camera"]["rvec"]), tvec: v3(&q["camera"]["tvec"]) };
    // Measured on the quick demo (a 7 × 4 board at 80 × 60 px): 2.4 mm off at 350 mm, the
    // optical axis 0.39° off.
    let (a, b) = (fitted_pose.camera_centre(), pose.camera_centre());
    let off = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    assert!(off < 5.0, "camera centre {a:?} against the scene's {b:?}");
    let (za, zb) = (fitted_pose.rotation()[2], pose.rotation()[2]);
    let axis_deg = (za[0] * zb[0] + za[1] * zb[1] + za[2] * zb[2]).clamp(-1.0, 1.0).acos().to_degrees();
    assert!(axis_deg < 1.0, "optical axis {axis_deg}° off the scene's");
    assert_eq!(q["warnings"], serde_json::json!([]), "{q}");
    let layers = lightrig_imaging::io::read_exr_layers(out.join("fit/maps.exr")).unwrap();
    let layer = |name: &str| layers.iter().find(|l| l.name == name);
    let v = layer("valid.roughness").expect("a valid.roughness layer");
    let from_file: Vec<bool> = v.image.data.iter().map(|&x| x == 1.0).collect();
    assert_eq!(from_file, valid.roughness);
    for name in ["height", "normal", "translucency"] {
        assert!(layer(name).is_some(), "{name}");
    }

    // The same session with its stripe and backlit passes taken out of the plan (as if never
    // acquired): heights and translucency are not measured, so not written; the diagonal
    // passes still give the normals.
    let bare = out.join("bare-session");
    copy_dir(&out.join("session"), &bare);
    let manifest = bare.join("manifest.json");
    let mut j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    for step in j["plan"]["steps"].as_array_mut().unwrap() {
        if matches!(step["extra"]["meta"]["pass"].as_str(), Some("stripe" | "backlit")) {
            step["extra"]["meta"]["pass"] = "not-acquired".into();
        }
    }
    std::fs::write(&manifest, serde_json::to_string_pretty(&j).unwrap()).unwrap();
    let bare_maps = lightrig_host::fit::lls::fit_session(
        &bare,
        Some(&out.join("camera.toml")),
        &out.join("bare-scratch"),
        &|_, _| {},
    )
    .unwrap();
    assert_eq!(
        bare_maps.measured,
        lightrig_host::fit::lls::Measured { height: false, normals: true, translucency: false }
    );
    let files = write_outputs(&bare_maps, &out.join("bare-fit")).unwrap();
    let names: Vec<String> =
        files.iter().map(|f| f.file_name().unwrap().to_string_lossy().into_owned()).collect();
    for absent in ["height.png", "translucency.png"] {
        assert!(
            !names.iter().any(|n| n == absent) && !out.join("bare-fit").join(absent).exists(),
            "{absent}"
        );
    }
    assert!(names.iter().any(|n| n == "normal.png"));
    let layers = lightrig_imaging::io::read_exr_layers(out.join("bare-fit/maps.exr")).unwrap();
    let names: Vec<&str> = layers.iter().map(|l| l.name.as_str()).collect();
    assert!(
        !names.contains(&"height") && !names.contains(&"translucency") && names.contains(&"normal"),
        "{names:?}"
    );
    let bare_valid = quality::validity(&bare_maps);
    assert!(!bare_valid.height.iter().any(|&v| v) && !bare_valid.translucency.iter().any(|&v| v));
    let q = quality::assess(&bare_maps, &bare_valid);
    assert_eq!(q.unmeasured.len(), 2, "{:?}", q.unmeasured);
    assert!(q.unmeasured[0].starts_with("height: the session has no stripe pass"), "{:?}", q.unmeasured);
    assert!(q.unmeasured[1].starts_with("translucency: "), "{:?}", q.unmeasured);
    // Without the diagonal passes too nothing gave normals: the renderer exports carry no
    // normal map (a flat one would read as measured), and still load whole.
    let mut j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    for step in j["plan"]["steps"].as_array_mut().unwrap() {
        let m = &mut step["extra"]["meta"];
        if m["pass"] == "reflectance" && m["mount_deg"].as_i64().unwrap_or(0) != 0 {
            m["pass"] = "not-acquired".into();
        }
    }
    std::fs::write(&manifest, serde_json::to_string_pretty(&j).unwrap()).unwrap();
    let flat = lightrig_host::fit::lls::fit_session(
        &bare,
        Some(&out.join("camera.toml")),
        &out.join("flat-scratch"),
        &|_, _| {},
    )
    .unwrap();
    assert!(!flat.measured.normals && flat.diagonal_mounts.is_empty(), "{:?}", flat.measured);
    let dir = out.join("flat-fit");
    write_outputs(&flat, &dir).unwrap();
    for absent in ["normal.png", "mitsuba/normal.exr", "gltf/normal.png"] {
        assert!(!dir.join(absent).exists(), "{absent}");
    }
    let xml = std::fs::read_to_string(dir.join("mitsuba/scene.xml")).unwrap();
    assert!(
        !xml.contains("normalmap") && xml.contains("No normal map") && xml.contains("blendbsdf"),
        "{xml}"
    );
    let gltf: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("gltf/sample.gltf")).unwrap()).unwrap();
    let material = &gltf["materials"][0];
    assert!(material.get("normalTexture").is_none(), "{material}");
    // Every texture the material names is one of the three images written.
    let images: Vec<&str> =
        gltf["images"].as_array().unwrap().iter().map(|i| i["uri"].as_str().unwrap()).collect();
    assert_eq!(images, ["base_color.png", "metallic_roughness.png", "specular_color.png"]);
    for (name, index) in [
        ("base_color.png", &material["pbrMetallicRoughness"]["baseColorTexture"]["index"]),
        ("metallic_roughness.png", &material["pbrMetallicRoughness"]["metallicRoughnessTexture"]["index"]),
        (
            "specular_color.png",
            &material["extensions"]["KHR_materials_specular"]["specularColorTexture"]["index"],
        ),
    ] {
        let source = &gltf["textures"][index.as_u64().unwrap() as usize]["source"];
        assert_eq!(images[source.as_u64().unwrap() as usize], name);
        assert!(dir.join("gltf").join(name).exists(), "{name}");
    }
    // With normals measured, the same export names the normal map beside them.
    let full: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("bare-fit/gltf/sample.gltf")).unwrap())
            .unwrap();
    let n = full["materials"][0]["normalTexture"]["index"].as_u64().unwrap() as usize;
    assert_eq!(full["images"][full["textures"][n]["source"].as_u64().unwrap() as usize]["uri"], "normal.png");
}

/// The report's figures (truth | fit | error per map) and its HTML page: every map shown, and
/// the pixels of the roughness figure's fit panel are the fitted α through the colour map,
/// grey outside the sample.
fn the_figures_show_the_maps(out: &std::path::Path, m: &lightrig_host::fit::lls::LlsMaps, scene: &LlsScene) {
    use lightrig_imaging::figure::{viridis, MASKED};
    let text = std::fs::read_to_string(out.join("report.md")).unwrap();
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    for map in ["diffuse", "specular", "roughness", "height", "normal", "translucency"] {
        assert!(text.contains(&format!("](fit/compare-{map}.png)")), "{map} in report.md");
        assert!(html.contains(&format!("<img src=\"fit/compare-{map}.png\"")), "{map} in report.html");
    }
    assert!(html.starts_with("<!DOCTYPE html>") && html.contains("<table>"), "{html}");
    let img = lightrig_imaging::io::read(out.join("fit/compare-roughness.png")).unwrap();
    let (w, h) = (m.width, m.height);
    let zoom = (240 / w).max(1);
    // Three panels with a gap of one zoom between, and the colour bars beneath.
    assert_eq!((img.width, img.height), (3 * w * zoom + 2 * zoom, h * zoom + 3 * zoom));
    let px = |x: u32, y: u32| -> [f32; 3] {
        let i = ((y * img.width + x) * 3) as usize;
        [img.data[i], img.data[i + 1], img.data[i + 2]]
    };
    let (mut shown, mut masked) = (0, 0);
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            let got = px(w * zoom + zoom + x * zoom + zoom / 2, y * zoom + zoom / 2);
            let want = if scene.truth[i].region == Region::Sample && m.fitted[i] {
                shown += 1;
                viridis(m.fit[i].alpha as f32 / 0.32)
            } else {
                masked += 1;
                MASKED
            };
            assert!(
                (0..3).all(|c| (got[c] - want[c]).abs() <= 0.6 / 255.0),
                "pixel ({x}, {y}): {got:?} for {want:?}"
            );
        }
    }
    assert!(shown > 1500 && masked > 100, "{shown} shown, {masked} masked");
}

/// A camera with a display gamma: with the response recovered from an exposure series and
/// named in the rig file, the fit meets every target; the same session merged as if the
/// camera were linear misses them.
#[test]
fn a_gamma_camera_fits_with_its_response_and_misses_without() {
    let out = std::env::temp_dir().join(format!("lightrig-demo-gamma-test-{}", std::process::id()));
    let opts = DemoOptions {
        quick: true,
        out: out.clone(),
        seed: 3,
        progress: false,
        real_time: false,
        step_mm: None,
        camera_gamma: Some(2.2),
    };
    let (acc, report) = run_lls(&opts).unwrap();
    for (name, value, limit, met) in acc.targets() {
        assert!(met, "with the response: {name}: {value} > {limit}");
    }
    assert!(std::fs::read_to_string(report).unwrap().contains("display gamma 2.2"));
    let rig = std::fs::read_to_string(out.join("rig.toml")).unwrap();
    assert!(rig.contains("gamma = 2.2") && rig.contains("response = \"camera-response.json\""), "{rig}");
    // The session kept its copy of the response; without it the fit refuses, naming the copy.
    let copy = out.join("session/camera0-response.json");
    let kept = lightrig_host::response::ResponseFile::load(&copy).unwrap();
    assert_eq!(kept, lightrig_host::response::ResponseFile::load(&out.join("camera-response.json")).unwrap());
    std::fs::remove_file(&copy).unwrap();
    let fit = |dir: &str| {
        lightrig_host::fit::lls::fit_session(
            &out.join("session"),
            Some(&out.join("camera.toml")),
            &out.join(dir),
            &|_, _| {},
        )
    };
    let e = fit("none").unwrap_err().to_string();
    assert!(e.contains("camera0-response.json") && e.contains("copy the response file there"), "{e}");
    // A linear response in its place: the brackets merged as a linear camera's.
    let levels = kept.levels;
    let g: Vec<f32> = (0..levels).map(|z| (z.max(1) as f32).ln()).collect();
    lightrig_host::response::ResponseFile { levels, g: vec![g.clone(), g.clone(), g] }.save(&copy).unwrap();
    let linear = fit("linear").unwrap();
    let scene = LlsScene::new(LlsSceneSpec::new(80, 60));
    let wrong = lightrig_cli::demo::lls::lls_accuracy(&scene, &linear, 2.0);
    let missed: Vec<_> = wrong.targets().into_iter().filter(|t| !t.3).map(|t| t.0).collect();
    assert!(
        missed.contains(&"diffuse albedo, median abs") && missed.contains(&"roughness, median rel"),
        "merged as linear, the fit should miss: {wrong:?}"
    );
    std::fs::remove_dir_all(&out).ok();
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

/// Every map of two fits, bit for bit (NaN equal to NaN).
fn assert_same_maps(a: &lightrig_host::fit::lls::LlsMaps, b: &lightrig_host::fit::lls::LlsMaps) {
    assert_eq!((a.width, a.height), (b.width, b.height));
    assert_eq!(a.fitted, b.fitted);
    assert_eq!(a.fit, b.fit);
    assert_eq!(a.points, b.points);
    assert_eq!(a.normals, b.normals);
    assert_eq!(a.geometric_normals, b.geometric_normals);
    assert_eq!(a.photometric_normals, b.photometric_normals);
    // GGX where both fitted it.
    if let (Some(x), Some(y)) = (&a.ggx, &b.ggx) {
        assert_eq!(x, y);
    }
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.translucency), bits(&b.translucency));
    assert_eq!(a.scale, b.scale);
    assert_eq!(a.specular_strip.0.to_bits(), b.specular_strip.0.to_bits());
    assert_eq!(a.check_frame.0, b.check_frame.0);
    assert_eq!(bits(&a.check_frame.1), bits(&b.check_frame.1));
    assert_eq!(bits(&a.check_frame.2), bits(&b.check_frame.2));
}

fn state(pass: Option<&str>, gantry: f64, lasers: u8) -> RigState {
    RigState {
        pass: pass.map(str::to_string),
        mount_deg: 0.0,
        axes: vec![gantry],
        lasers,
        filters: vec![],
        exposure_s: 0.004,
        ..RigState::default()
    }
}

#[test]
fn a_white_plate_under_the_tube_matches_the_view_factor() {
    // A Lambertian strip (the diffuse calibration strip, ρ = 0.8) under the tube: radiance
    // ρ·Le·r·h/(h² + Δx²), the closed form for an infinitely long tube; the tube is made 200 m
    // long so that its ends cost nothing.
    let mut spec = LlsSceneSpec::new(80, 60);
    spec.light.length_mm = 2e5;
    let scene = LlsScene::new(spec.clone());
    let (w, _) = scene.size();
    let mut checked = 0;
    for (i, t) in scene.truth.iter().enumerate() {
        if t.region != Region::DiffuseStrip {
            continue;
        }
        let g = t.point[0] + 40.0; // on the far side from the camera: never in its way
        let l = scene.radiance(i as u32 % w, i as u32 / w, &state(None, g, 1 << spec.tube_channel));
        let (r, h) = (spec.light.diameter_mm / 2.0, spec.light.height_mm);
        let dx = t.point[0] - g;
        let want = 0.8 * spec.light.radiance * r * h / (h * h + dx * dx);
        for c in l {
            assert!((c / want - 1.0).abs() < 1e-5, "pixel {i}: {c} vs {want}");
        }
        checked += 1;
    }
    assert!(checked > 50, "{checked} strip pixels");
}

#[test]
fn the_stripe_lights_the_points_on_the_sheet() {
    // Every sample pixel is brightest in the stripe when the sheet passes through its point.
    let spec = LlsSceneSpec::new(40, 30);
    let scene = LlsScene::new(spec.clone());
    let (w, _) = scene.size();
    let tan = spec.stripe.angle_deg.to_radians().tan();
    for (i, t) in scene.truth.iter().enumerate().filter(|(_, t)| t.region == Region::Sample) {
        let g = t.point[0] - spec.stripe.offset_mm - t.point[2] * tan;
        let at =
            |g: f64| scene.radiance(i as u32 % w, i as u32 / w, &state(None, g, 1 << spec.stripe_channel))[0];
        let peak = at(g);
        assert!(peak > 0.0);
        assert!(at(g + 0.3) < peak && at(g - 0.3) < peak, "pixel {i}");
        let want = spec.stripe.radiance * t.material.diffuse[0];
        assert!((peak / want - 1.0).abs() < 1e-9, "pixel {i}: {peak} vs {want}");
    }
}

#[test]
fn same_seed_same_bytes() {
    let spec = LlsSceneSpec::new(24, 18);
    let scene = LlsScene::new(spec.clone());
    let s = Sensor { seed: 3, ..Sensor::default() };
    let frame = |sensor: &Sensor, key: u64| -> Vec<u32> {
        let st = state(None, -10.0, 1 << spec.tube_channel);
        let (w, h) = scene.size();
        (0..w * h)
            .flat_map(|i| {
                let l = scene.radiance(i % w, i / w, &st);
                (0..3).map(move |c| (i, c, l[c]))
            })
            .map(|(i, c, l)| sensor.expose(l, 0.004, key * 1_000_000 + u64::from(i) * 3 + c as u64).to_bits())
            .collect()
    };
    assert_eq!(frame(&s, 5), frame(&s, 5));
    assert_ne!(frame(&s, 5), frame(&s, 6));
    assert_ne!(frame(&s, 5), frame(&Sensor { seed: 4, ..s }, 5));
}
