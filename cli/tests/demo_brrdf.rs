//! The bispectral BRRDF end to end: the quick demo (a Spectralon session and the two spheres on
//! the virtual rig, `lightrig fit brrdf`'s pipeline) against the scene's band-limited truth, and
//! the fit's errors on bad input.

use lightrig_cli::demo::brrdf::{
    run_brrdf, BrrdfDemoOptions, DIAGONAL_TOLERANCE, MIN_PSNR, RERADIATION_TOLERANCE,
};
use lightrig_host::fit::brrdf::fit_session;

#[test]
fn the_quick_brrdf_demo_scales_bins_and_reconstructs_against_the_truth() {
    let out = std::env::temp_dir().join(format!("lightrig-brrdf-demo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let opts = BrrdfDemoOptions { quick: true, out: out.clone(), seed: 1, progress: false, real_time: false };
    let r = run_brrdf(&opts).unwrap();
    // The shipped grid: LEDs 380-460 and the xenon 480-720 nm in, 400-720 nm out, 20 nm steps
    // (the thesis's 170 pairs); 380 nm has no Spectralon diagonal and is left out, said so.
    assert_eq!(r.fit.pairs.len(), 170 - 17);
    assert!(r.fit.notes.iter().any(|n| n.contains("excitation 380 nm left out")), "{:?}", r.fit.notes);
    assert_eq!(r.fit.spheres.len(), 2);
    for (k, t) in r.truth.iter().enumerate() {
        assert!(t.diagonal <= DIAGONAL_TOLERANCE, "sphere {k}: diagonal {}", t.diagonal);
        assert!(t.entries[0] > 1000, "sphere {k}: {} diagonal entries compared", t.entries[0]);
    }
    // Only the fluorescent sphere reradiates, and its reradiation is scaled right.
    assert!(r.truth[0].reradiation.is_nan() || r.truth[0].entries[1] == 0);
    assert!(r.truth[1].reradiation <= RERADIATION_TOLERANCE, "{}", r.truth[1].reradiation);
    assert!(r.truth[1].entries[1] > 1000);
    // The angle left out of the PCA set, from five pairs.
    let t = r.fit.spheres[1].transfer.as_ref().unwrap();
    assert_eq!(t.chosen_saturated.len(), 5);
    assert!(!r.fit.pca_angles.iter().any(|a| (a - t.held_out_deg).abs() < 0.01));
    assert!(t.psnr_saturated[0] >= MIN_PSNR, "saturated PCA, non-specular: {} dB", t.psnr_saturated[0]);
    // Binned: every bin filled, the observed ones counted.
    for s in &r.fit.spheres {
        assert!(s.binned.observed() > 300, "{}", s.binned.observed());
        assert!(s.binned.values.iter().all(|v| v.is_finite()));
    }
    let report = std::fs::read_to_string(&r.report).unwrap();
    assert!(report.contains("## Per sphere") && report.contains("excitation 380 nm left out"));
    for f in ["brrdf-top.json", "brrdf-top.f32", "brrdf-bottom.json", "pca-bottom.json", "scaling.json"] {
        assert!(out.join("fit").join(f).exists(), "{f}");
    }
    let len = std::fs::metadata(out.join("fit/brrdf-bottom.f32")).unwrap().len();
    assert_eq!(len, 32u64.pow(3) * 153 * 4, "32³ bins × 153 pairs × f32");

    // Bad input: no Spectralon session, and a sphere session given as the Spectralon one.
    let spheres = out.join("spheres/session");
    let e = fit_session(&spheres, None, &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("no Spectralon session") && e.contains("--spectralon"), "{e}");
    let e = fit_session(&spheres, Some(&out.join("nowhere")), &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("nowhere") && e.contains("Spectralon session is missing"), "{e}");
    let e = fit_session(&spheres, Some(&spheres), &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("not a Spectralon session"), "{e}");
    let _ = std::fs::remove_dir_all(&out);
}
