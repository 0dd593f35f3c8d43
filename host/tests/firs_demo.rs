//! Fluorescent immersion range scanning end to end on the virtual rig: the quick demo (an
//! opaque sphere behind a refracting wall) acquired, calibrated and fitted, checked against the
//! scene's ground truth; the tank scene's renders checked for determinism.

use lightrig_host::firs_demo::{firs_accuracy, run_firs, FirsDemoOptions};
use lightrig_host::virtual_rig::camera::{RigState, VirtualCamera};
use lightrig_host::virtual_rig::firs_scene::{FirsScene, FirsSceneSpec};
use lightrig_host::virtual_rig::sensor::Sensor;
use lightrig_pipelines::firs::mesh::read_ply;

#[test]
fn firs_quick_demo_meets_the_accuracy_targets() {
    let out = std::env::temp_dir().join(format!("lightrig-firs-demo-test-{}", std::process::id()));
    let opts = FirsDemoOptions { quick: true, out: out.clone(), seed: 5, progress: false };
    let (acc, report) = run_firs(&opts).unwrap();
    // The target: 0.05 % of the sphere's 32 mm (16 µm) RMS. Measured: about 4.7 µm.
    assert!(acc.rms_percent() <= 0.05, "{acc:?}");
    for (name, value, limit, met) in acc.targets() {
        assert!(met, "{name}: {value} against {limit}");
    }
    // Most of the surface the camera sees lit is recovered, and from one orientation.
    assert_eq!(acc.orientations.len(), 1);
    assert!(acc.merged.0 > 5000, "{acc:?}");
    // The calibration itself against the truth: rays through the wall to a few µm (measured
    // 1.2 µm), sheets to well under the sheet spacing of 140 µm (measured 5 µm RMS).
    assert!(acc.ray_rms_mm < 0.005, "{acc:?}");
    assert!(acc.sheet_err_mm.0 < 0.015, "{acc:?}");
    let text = std::fs::read_to_string(report).unwrap();
    assert!(text.contains("| RMS distance to the true surface, % of size |"), "{text}");
    for f in ["rig.toml", "truth/scene.json", "session/journal.jsonl", "fit/summary.json"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // The PLY files hold the points: the merged set has every recovered point.
    let merged = read_ply(&mut std::fs::File::open(out.join("fit/merged.ply")).unwrap()).unwrap();
    assert_eq!(merged.vertices.len(), acc.merged.0);
    let mesh = read_ply(&mut std::fs::File::open(out.join("fit/orientation_00.ply")).unwrap()).unwrap();
    assert!(mesh.triangles.len() > merged.vertices.len(), "{} triangles", mesh.triangles.len());

    // `lightrig fit firs-surface` on the session gives the same result.
    let again = lightrig_host::firs_fit::fit_surface(&out.join("session"), &|_, _| {}).unwrap();
    let spec: FirsSceneSpec =
        serde_json::from_str(&std::fs::read_to_string(out.join("truth/scene.json")).unwrap()).unwrap();
    assert_eq!(firs_accuracy(&spec, &again), acc);

    // The check can fail: the same points against a sphere 0.1 mm larger are far off target.
    let mut bigger = spec.clone();
    bigger.sphere_radius += 0.1;
    let off = firs_accuracy(&bigger, &again);
    assert!(off.merged.1 > 0.08, "{off:?}");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn tank_frames_are_deterministic_given_the_seed() {
    let spec = FirsSceneSpec::new(64, 48);
    let rig_text = lightrig_host::firs_demo::firs_rig_text(&spec, (30000, 36000, 10), 1);
    let rig = lightrig_host::rigfile::RigFile::parse(&rig_text, std::path::Path::new("rig.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("lightrig-firs-det-{}", std::process::id()));
    let cam = |seed| {
        let sensor = Sensor { gain: 1e6, seed, ..Sensor::default() };
        VirtualCamera::new(&rig, 0, FirsScene::new(spec.clone()), sensor, 1_000_000, &dir).unwrap()
    };
    let state = RigState {
        pass: Some("scan".into()),
        axes: vec![0.0],
        lasers: 1,
        exposure_s: 0.02,
        // The sheet 2 mm in front of the sphere on the optical axis.
        galvos: vec![[spec.code_for_depth(-18.0).round() as u16, 32768]],
        ..RigState::default()
    };
    let bits = |img: lightrig_imaging::io::Image| img.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    let a = bits(cam(3).render(&state, 17));
    assert_eq!(a, bits(cam(3).render(&state, 17)), "same seed, same frame");
    assert_ne!(a, bits(cam(4).render(&state, 17)), "another seed, other noise");
    // The sheet glows in front of the sphere; behind it (which the whole small field sees
    // through the sphere) only the weak stray light is left.
    let green =
        |bits: &[u32]| bits.iter().skip(1).step_by(3).map(|&b| f32::from_bits(b)).fold(0f32, f32::max);
    assert!(green(&a) > 0.5, "{}", green(&a));
    let behind =
        RigState { galvos: vec![[spec.code_for_depth(30.0).round() as u16, 32768]], ..state.clone() };
    let b = bits(cam(3).render(&behind, 17));
    assert!(green(&b) < 0.05, "{}", green(&b));
    std::fs::remove_dir_all(&dir).ok();
}
