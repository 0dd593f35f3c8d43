//! The PCA-steered bispectral acquisition through the command line, as a lab runs it: the
//! spheres' session stops before its first chosen-pair step because the Spectralon session it
//! scales by is not there yet; once it is, `lightrig resume` makes the choice, takes the chosen
//! pairs and completes the one session, and `lightrig fit brrdf` reconstructs the other angle.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

fn lightrig(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig")).args(args).stdin(Stdio::null()).output().unwrap()
}

fn said(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).to_string() + &String::from_utf8_lossy(&out.stdout)
}

/// `lightrig acquire` of the shipped bispectral rig, small: camera 400–480 nm (20 pairs with
/// the LEDs and the xenon's 480 nm), `sets` added.
fn acquire(session: &Path, sets: &[&str]) -> Output {
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/bispectral.toml");
    let mut args: Vec<String> =
        vec!["acquire".into(), rig.display().to_string(), "--session".into(), session.display().to_string()];
    for s in ["plan.tunable_filter.range_nm=[400, 480]"].iter().chain(sets) {
        args.push("--set".into());
        args.push(s.to_string());
    }
    lightrig(&args.iter().map(String::as_str).collect::<Vec<_>>())
}

#[test]
fn a_steered_session_waits_for_its_spectralon_session_then_resumes_chooses_and_fits() {
    let dir: PathBuf = std::env::temp_dir().join(format!("lightrig-steered-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (spheres, cal) = (dir.join("spheres"), dir.join("cal"));
    let steer = [
        "plan.gonio.light_angles=[0, 70, 100]",
        "plan.steer.dense_angles=[0, 70]",
        "plan.steer.select=3",
        "plan.fit.pca_angles=[0, 70]",
        "plan.fit.spectralon=\"../cal\"",
    ];
    let first = acquire(&spheres, &steer);
    let text = said(&first);
    assert!(!first.status.success(), "{text}");
    assert!(text.contains("Spectralon session is missing") && text.contains("lightrig resume"), "{text}");
    assert!(text.contains("optical exposure"), "{text}");
    let (s, _) = lightrig_host::session::Session::read(&spheres).unwrap();
    assert_eq!(s.steps_done().len(), 2 * 20, "the dense angles are in, nothing of the chosen ones");
    assert!(!spheres.join(lightrig_host::steer::CHOICE_FILE).exists());

    let c = acquire(&cal, &["plan.sample=\"spectralon\"", "plan.gonio.light_angles=[0]"]);
    assert!(c.status.success(), "{}", said(&c));
    let resumed = lightrig(&["resume", spheres.to_str().unwrap()]);
    assert!(resumed.status.success(), "{}", said(&resumed));
    let choice = lightrig_host::steer::Choice::load(&spheres).unwrap().expect("chosen at resume");
    assert_eq!(choice.pairs.len(), 3);
    let (s, _) = lightrig_host::session::Session::read(&spheres).unwrap();
    assert!(s.is_done());
    assert_eq!(s.manifest().plan.steps.len(), 2 * 20 + 3);
    assert_eq!(s.frame_index().len(), (2 * 20 + 3) * 3, "three exposures a step, every one paired");

    let out = dir.join("fit");
    let fit = lightrig(&["fit", "brrdf", spheres.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let text = said(&fit);
    assert!(fit.status.success(), "{text}");
    let reconstructed: Vec<usize> =
        text.lines().filter_map(|l| l.split(" samples (").nth(1)?.split(' ').next()?.parse().ok()).collect();
    assert_eq!(reconstructed.len(), 2, "{text}");
    assert!(reconstructed.iter().all(|&n| n > 100), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_series_clipped_in_every_exposure_is_named_with_what_to_do() {
    let dir: PathBuf = std::env::temp_dir().join(format!("lightrig-clipped-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let spheres = dir.join("spheres");
    // One exposure 64 times what fills half the well on white: the spheres clip.
    let a = acquire(&spheres, &["plan.gonio.light_angles=[0]", "plan.exposures_us=[1280000]"]);
    assert!(a.status.success(), "{}", said(&a));
    let out = dir.join("fit");
    let fit = lightrig(&[
        "fit",
        "brrdf",
        spheres.to_str().unwrap(),
        "--spectralon",
        dir.join("cal").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = said(&fit);
    assert!(!fit.status.success(), "{text}");
    assert!(text.contains("clipped in every exposure") && text.contains("shorter exposure"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}
