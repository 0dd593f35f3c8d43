//! The bispectral BRRDF end to end: the quick demo (a Spectralon session and the two spheres on
//! the virtual rig, `lightrig fit brrdf`'s pipeline) against the scene's band-limited truth, and
//! the fit's errors on bad input.

mod kept_demo;

use lightrig_cli::demo::brrdf::{
    run_brrdf, BrrdfDemoOptions, DIAGONAL_TOLERANCE, MAX_COMPONENTS, MIN_PSNR, RERADIATION_TOLERANCE,
    SPARSE_MIN_PSNR,
};
use lightrig_host::fit::brrdf::fit_session;

#[test]
fn the_quick_brrdf_demo_scales_bins_and_reconstructs_against_the_truth() {
    let out = kept_demo::out_dir("brrdf", "lightrig-brrdf-demo");
    let opts = BrrdfDemoOptions { quick: true, out: out.clone(), seed: 1, progress: false, real_time: false };
    let r = run_brrdf(&opts).unwrap();
    // Every target `lightrig demo brrdf --check` holds the demo to (CI runs the demos here).
    assert!(r.missed().is_empty(), "{:?}", r.targets());
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
    // Same angle: every PCA angle (0°, 70°, 140°) decomposed, each within the target.
    let same = &r.fit.spheres[1].same_angle;
    assert_eq!(same.len(), 3, "{same:?}");
    assert!(same.iter().all(|a| a.components_1pc <= MAX_COMPONENTS), "{same:?}");
    assert!(
        same.iter().any(|a| a.components_1pc > 1),
        "the fluorescent sphere's 70° slice is not rank one: {same:?}"
    );
    // The angle left out of the PCA set, from five pairs.
    let t = r.fit.spheres[1].transfer.as_ref().unwrap();
    assert_eq!(t.chosen_saturated.len(), 5);
    assert!(!r.fit.pca_angles.contains(&t.held_out_deg));
    assert!((t.held_out_deg - 35.0).abs() < 0.01, "between the first two PCA angles: {}", t.held_out_deg);
    for a in [0.0, 70.0, 140.0] {
        assert!(r.fit.pca_angles.iter().any(|p| (p - a).abs() < 0.01), "{:?}", r.fit.pca_angles);
    }
    assert!(t.psnr_saturated[0] >= MIN_PSNR, "saturated PCA, non-specular: {} dB", t.psnr_saturated[0]);
    // The loop closed in the one session: the PCA chose five pairs once the dense angles were
    // in; the other two angles took only those, and came back whole through the PCA.
    let choice =
        lightrig_host::steer::Choice::load(&out.join("spheres/session")).unwrap().expect("the choice");
    assert_eq!(choice.pairs.len(), 5);
    assert_eq!(choice.from_light_deg.len(), 4, "{:?}", choice.from_light_deg);
    let (s, _) = lightrig_host::session::Session::read(out.join("spheres/session")).unwrap();
    assert!(s.is_done());
    assert_eq!(s.manifest().plan.steps.len(), 4 * 170 + 2 * 5);
    for sphere in &r.fit.spheres {
        let angles: std::collections::BTreeSet<i64> =
            sphere.samples.iter().filter(|x| x.reconstructed).map(|x| x.light_deg.round() as i64).collect();
        assert_eq!(angles.into_iter().collect::<Vec<_>>(), [100, 120], "{}", sphere.name);
        assert!(sphere.reconstructed > 100, "{}: {}", sphere.name, sphere.reconstructed);
    }
    for (k, p) in r.sparse_psnr.iter().enumerate() {
        assert!(*p >= SPARSE_MIN_PSNR, "sphere {k}: reconstructed angles {p} dB against the truth");
    }
    assert!(r.exposure_s.0 < 0.7 * r.exposure_s.1, "{:?}", r.exposure_s);
    // Binned: every bin filled, the observed ones counted.
    for s in &r.fit.spheres {
        assert!(s.binned.observed() > 300, "{}", s.binned.observed());
        assert!(s.binned.values.iter().all(|v| v.is_finite()));
    }
    // The spectral images read back as the fit's samples (×π), and the renderings: under the
    // 400 nm LED the fluorescent sphere glows green, the orange coat stays dark.
    use lightrig_host::fit::brrdf::{render, spectral_image, RENDER_ILLUMINANTS};
    use lightrig_imaging::io::BispectralImage;
    let exr = BispectralImage::read(out.join("fit/spectral-0deg.exr")).unwrap();
    assert_eq!(exr, spectral_image(&r.fit, r.fit.pca_angles[0]));
    assert_eq!(exr.diagonal.len() + exr.reradiation.len(), 153);
    let centre = |k: usize| {
        let d = r.fit.spheres[k].disc;
        (d.cy as usize) * r.fit.size.0 as usize + d.cx as usize
    };
    let uv = render(&r.fit, r.fit.pca_angles[0], RENDER_ILLUMINANTS[2]);
    let (top, bottom) = (uv[centre(0)], uv[centre(1)]);
    assert!(bottom[1] > bottom[0] && bottom[1] > bottom[2], "green glow: {bottom:?}");
    assert!(bottom[1] > 10.0 * top[1].max(1e-6), "fluorescent {bottom:?} against {top:?}");
    let day = render(&r.fit, r.fit.pca_angles[0], RENDER_ILLUMINANTS[0])[centre(0)];
    assert!(day[0] > day[1] && day[1] > day[2], "orange in daylight: {day:?}");
    // Each sphere's reradiation matrix, one pixel per PCA angle, reads back as written.
    let m = BispectralImage::read(out.join("fit/reradiation-bottom.exr")).unwrap();
    assert_eq!(m, lightrig_host::fit::brrdf::sphere_matrix(&r.fit, 1));
    assert_eq!(
        (m.width, m.height, m.diagonal.len() + m.reradiation.len()),
        (r.fit.pca_angles.len() as u32, 1, 153)
    );
    for f in [
        "render-d65.png",
        "render-a.png",
        "render-led400.png",
        "spectral-70deg.exr",
        "spectral-140deg.exr",
        "reradiation-top.exr",
    ] {
        assert!(out.join("fit").join(f).exists(), "{f}");
    }
    let report = std::fs::read_to_string(&r.report).unwrap();
    assert!(report.contains("## Per sphere") && report.contains("excitation 380 nm left out"));
    // Each sphere's truth, fit and error at the camera's 160 × 100 (zoom 3) with their colour
    // bars, masked alike off the sphere's samples.
    for name in ["top", "bottom"] {
        assert!(report.contains(&format!("![truth, fit, relative error](fit/compare-{name}.png)")), "{name}");
        let fig = lightrig_imaging::io::read(out.join(format!("fit/compare-{name}.png"))).unwrap();
        assert_eq!((fig.width, fig.height), (3 * 3 * 160 + 2 * 3, 3 * 100 + 3 * 3), "{name}");
        let masked = |x: u32, y: u32| {
            let i = ((y * fig.width + x) * u32::from(fig.channels)) as usize;
            (0..3).all(|c| (fig.data[i + c] - lightrig_imaging::figure::MASKED[c]).abs() < 0.01)
        };
        let shown = |panel: u32| {
            (0..100)
                .flat_map(|y| (0..160).map(move |x| (x, y)))
                .filter(|&(x, y)| !masked(3 * (panel * 161 + x), 3 * y))
                .count()
        };
        let (t, e) = (shown(0), shown(2));
        assert!(t > 500 && t == e, "{name}: {t} truth pixels, {e} error pixels");
    }
    for f in ["brrdf-top.json", "brrdf-top.f32", "brrdf-bottom.json", "pca-bottom.json", "scaling.json"] {
        assert!(out.join("fit").join(f).exists(), "{f}");
    }
    let len = std::fs::metadata(out.join("fit/brrdf-bottom.f32")).unwrap().len();
    assert_eq!(len, 32u64.pow(3) * 153 * 4, "32³ bins × 153 pairs × f32");

    // Bad input: no Spectralon session (the calibration session's own rig names none), a
    // missing one, and a sphere session given as the Spectralon one.
    let spheres = out.join("spheres/session");
    let cal = out.join("spectralon/session");
    let e = fit_session(&cal, None, &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("no Spectralon session") && e.contains("--spectralon"), "{e}");
    // The steered session names its Spectralon session in [plan.fit]: no flag needed.
    assert_eq!(fit_session(&spheres, None, &|_, _| {}).unwrap().pairs, r.fit.pairs);
    let e = fit_session(&spheres, Some(&out.join("nowhere")), &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("nowhere") && e.contains("Spectralon session is missing"), "{e}");
    let e = fit_session(&spheres, Some(&spheres), &|_, _| {}).unwrap_err().to_string();
    assert!(e.contains("not a Spectralon session"), "{e}");
    // A PCA angle that was not acquired is named.
    let text = std::fs::read_to_string(out.join("spheres/rig.toml")).unwrap();
    let e = {
        use lightrig_host::fit::brrdf::{read, spectralon_rows, FitSpec, SPECTRALON};
        use lightrig_pipelines::brrdf::scaling::Scaling;
        let mut m = read(&spheres, &|_, _| {}).unwrap();
        m.rig = lightrig_host::rigfile::RigFile::parse(
            &text.replace("pca_angles = [0, 70, 140]", "pca_angles = [0, 65]"),
            &out.join("spheres/rig.toml"),
        )
        .unwrap();
        let spec = FitSpec::from_rig(&m.rig).unwrap();
        let cal = read(&out.join("spectralon/session"), &|_, _| {}).unwrap();
        let rows: Vec<_> = spectralon_rows(&cal).unwrap().into_iter().filter(|r| r.0 .0 != 380).collect();
        let scaling = Scaling::new(&rows, |nm| spec.band_integral(f64::from(nm)), 20.0, SPECTRALON).unwrap();
        m.steps.retain(|s| s.pair.0 != 380);
        lightrig_host::fit::brrdf::fit_merged(&m, scaling, spec).unwrap_err().to_string()
    };
    assert!(e.contains("pca_angles: 65°") && e.contains("70.0°"), "{e}");
    kept_demo::finish(&out);
}
