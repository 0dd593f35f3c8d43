//! The bispectral gonioreflectometer's virtual scene against its closed forms: Spectralon's
//! Lambertian diagonal, the coated sphere's highlight where the half vector says, and
//! fluorescence only from the fluorescent paint.

use std::path::Path;

use lightrig_host::overrides::{apply, Override};
use lightrig_host::rigfile::RigFile;
use lightrig_sim::camera::{RigState, Scene};
use lightrig_sim::scenes::bispectral::{BispectralScene, Sample};

fn rig(sets: &[&str]) -> RigFile {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/bispectral.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let sets: Vec<Override> = sets.iter().map(|s| s.parse().unwrap()).collect();
    RigFile::parse(&apply(&text, &sets).unwrap(), &path).unwrap()
}

/// The wheel at the slot named `slot`, the filters at `light_nm` / `camera_nm`, the light arm
/// at `light_deg`.
fn state(scene: &BispectralScene, slot: &str, light_nm: f64, camera_nm: f64, light_deg: f64) -> RigState {
    let s = scene.slots.iter().position(|n| n == slot).unwrap() as u8;
    let mut axes = vec![0.0; 2];
    axes[usize::from(scene.light_axis)] = light_deg;
    RigState {
        axes,
        filters: vec![Some(s)],
        exposure_s: 0.02,
        meta: serde_json::json!({ "host": { "light_filter_nm": light_nm, "camera_filter_nm": camera_nm } }),
        ..RigState::default()
    }
}

#[test]
fn spectralon_is_the_unit_and_lambertian() {
    let scene = BispectralScene::new(&rig(&["plan.sample=\"spectralon\""]), 160, 100);
    assert_eq!(scene.sample, Sample::Spectralon);
    let head_on = scene.radiance(80, 50, &state(&scene, "white", 550.0, 550.0, 0.0));
    assert!((head_on[0] - 1.0).abs() < 1e-12, "{head_on:?}");
    let tilted = scene.radiance(3, 97, &state(&scene, "white", 550.0, 550.0, 60.0));
    assert!((tilted[0] - 0.5).abs() < 1e-12, "cos 60°: {tilted:?}");
    assert_eq!(scene.radiance(80, 50, &state(&scene, "dark", 550.0, 550.0, 0.0)), [0.0; 3]);
}

#[test]
fn the_coated_sphere_shows_its_highlight_at_the_half_vector() {
    let scene = BispectralScene::new(&rig(&[]), 160, 100);
    let Sample::Spheres { radius } = scene.sample else { panic!("spheres") };
    for light_deg in [20.0f64, 40.0, 70.0] {
        let st = state(&scene, "white", 600.0, 600.0, light_deg);
        // The top sphere's brightest pixel.
        let (mut best, mut at) = (0.0, (0, 0));
        for y in 0..50 {
            for x in 0..160 {
                let v = scene.radiance(x, y, &st)[0];
                if v > best {
                    (best, at) = (v, (x, y));
                }
            }
        }
        // Half vector of (sin a, 0, cos a) and (0, 0, 1): at polar angle a/2 towards +x.
        let h = (light_deg / 2.0).to_radians();
        let want = (80.0 + radius * h.sin(), 100.0 * 0.27);
        let (dx, dy) = (f64::from(at.0) + 0.5 - want.0, f64::from(at.1) + 0.5 - want.1);
        assert!(
            dx.abs() <= 1.0 && dy.abs() <= 1.0,
            "light at {light_deg}°: peak {at:?}, half vector at {want:?}"
        );
    }
}

#[test]
fn only_the_fluorescent_sphere_glows_off_the_diagonal() {
    let scene = BispectralScene::new(&rig(&[]), 160, 100);
    let (top, bottom) = ((80, 27), (80, 73));
    // Blue LED in, green-yellow out: the fluorescent paint reradiates, the orange coat does not.
    let blue_in = state(&scene, "led-440", 440.0, 540.0, 0.0);
    let (t, b) = (scene.radiance(top.0, top.1, &blue_in)[0], scene.radiance(bottom.0, bottom.1, &blue_in)[0]);
    assert!(b > 1000.0 * t.max(1e-300), "fluorescent {b} against {t}");
    // On the diagonal at 540 nm both reflect; the reradiated light is a good part of it.
    let diagonal = state(&scene, "white", 540.0, 540.0, 0.0);
    let d = scene.radiance(bottom.0, bottom.1, &diagonal)[0];
    assert!(d > 0.0 && b > 0.0);
    // Nothing comes back shorter than it went in.
    let back = state(&scene, "white", 600.0, 500.0, 0.0);
    let v = scene.radiance(bottom.0, bottom.1, &back)[0];
    assert!(v < 1e-6 * d, "{v}");
}
