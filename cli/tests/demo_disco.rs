//! DISCO end to end: the quick demo (the white balance and the translucent pebble on the
//! virtual rig, `lightrig fit disco`'s pipeline) against the scene's true throughput factors,
//! `F`'s file read back, and the fit's errors on bad input.

mod kept_demo;

use lightrig_cli::demo::disco::{
    acquire_disco, projector_error, run_disco, DiscoDemoOptions, DETAIL_TOLERANCE, INTERPOLATED_TOLERANCE,
    KERNEL_TOLERANCE, OBSERVED_TOLERANCE, PROJECTOR_TOLERANCE_MM, REGISTRATION_TOLERANCE_MM,
};
use lightrig_host::fit::disco::{fit_session, read_matrix, ATLAS_FORMAT, F_FORMAT};

#[test]
fn the_quick_disco_demo_measures_f_against_the_truth() {
    let out = kept_demo::out_dir("disco", "lightrig-disco-demo");
    let opts = DiscoDemoOptions { quick: true, out: out.clone(), seed: 1, progress: false, real_time: false };
    let r = run_disco(&opts).unwrap();
    assert!(r.missed().is_empty(), "{:?}", r.targets());
    let (f, a) = (&r.fit, &r.accuracy);
    for c in 0..3 {
        assert!(a.observed[c] <= OBSERVED_TOLERANCE, "channel {c}: {:?}", a.observed);
        assert!(a.interpolated[c] <= INTERPOLATED_TOLERANCE, "channel {c}: {:?}", a.interpolated);
    }
    assert!(a.symmetric);
    assert!(a.entries[0] > 8_000 && a.entries[1] > 5_000 && a.entries[4] > 5_000, "{:?}", a.entries);
    // Where the skin's lines cross a vertex's fan, F holds the skin as the few spots there
    // entered it (6.1 % in blue at this seed): reported, bounded here against regressions.
    assert!(a.observed_lines.iter().all(|&e| e < 0.08), "{:?}", a.observed_lines);
    // 4 turntable views × 2 camera positions; 16 × 16 spots × 3 lasers each.
    assert_eq!((f.views, f.frames), (8, 8 * 256 * 3));
    // The scanned mesh (12° and 6 mm off) placed by the spotlit silhouettes of all 8 views.
    let g = f.registration.as_ref().expect("registered");
    assert_eq!((g.views_used, g.agreement.len()), (8, 8));
    assert!(g.min_iou() > 0.995, "{g:?}");
    let e = r.registration_error_mm.unwrap();
    assert!(e <= REGISTRATION_TOLERANCE_MM, "{e} mm");
    // The projector fitted to the spots of every view (the rig file has it right here; below,
    // the same session with the rig file's projector off).
    let p = &f.projector;
    assert!(r.projector_error_mm <= PROJECTOR_TOLERANCE_MM, "{} mm: {p:?}", r.projector_error_mm);
    assert!(p.used > 150 && p.rms_mm < 0.1 && p.dropped < p.used / 2, "{p:?}");
    assert_eq!(f.used + f.missed + f.held_out_frames, f.frames);
    // Spots the camera saw within 20° of their beam's mirror direction, where the scene's
    // glint shows (114 at this seed): their pixels near the spot left out, the spot not fitted.
    assert!(f.glint_frames > 50 && f.glint_frames < f.used / 10, "{} glint frames", f.glint_frames);
    assert!(f.used > 2000 && f.lit_columns > 400, "{} frames used, {} columns lit", f.used, f.lit_columns);
    // The white balance recovers the lasers' fluxes as the camera sees them (the scene's
    // 1 : 0.85 : 0.6) and the beam's width (σ 0.85 mm).
    assert!(
        (f.flux[1] / f.flux[0] - 0.85).abs() < 0.01 && (f.flux[2] / f.flux[0] - 0.6).abs() < 0.01,
        "{:?}",
        f.flux
    );
    assert!((f.beam_sigma_mm - 0.85).abs() < 0.05, "{}", f.beam_sigma_mm);
    // The spot's peak on the mesh lies within a fraction of a millimetre of the entry point.
    assert!(f.spots_seen > 1000 && f.peak_offset_mm < 0.5, "{} {}", f.spots_seen, f.peak_offset_mm);
    // Held-out spots: predicted from F beyond the near field (15.2 % at this seed).
    assert!(f.held_out.frames > 300 && f.held_out.median_rel_rms < 0.2, "{:?}", f.held_out);
    // Relit by a light no frame used, against the dipole integrated over the surface: the local
    // kernels carrying each vertex's one-ring do better than F's near entries (14.7 % against
    // 20.1 % at this seed), and the detail texture better than without it (17.6 %).
    assert!(
        r.relit_error < 0.2
            && r.relit_error < 0.9 * r.relit_global_error
            && r.relit_error < r.relit_plain_error,
        "{} {} {}",
        r.relit_error,
        r.relit_global_error,
        r.relit_plain_error
    );
    // The relit truth, fit and error side by side at twice the camera's 288 × 186, with the
    // error's colour bar beneath; the corner pixel is off the object: grey in the error panel.
    let fig = lightrig_imaging::io::read(out.join("fit/relit-figure.png")).unwrap();
    assert_eq!((fig.width, fig.height), (3 * 2 * 288 + 2 * 2, 2 * 186 + 3 * 2));
    let px = |x: u32, y: u32| {
        let i = ((y * fig.width + x) * u32::from(fig.channels)) as usize;
        [fig.data[i], fig.data[i + 1], fig.data[i + 2]]
    };
    let grey = lightrig_imaging::figure::MASKED;
    assert!(
        px(2 * (2 * 288 + 2) + 1, 1).iter().zip(grey).all(|(a, b)| (a - b).abs() < 0.01),
        "{:?}",
        px(1158, 1)
    );
    // The middle of the error panel's bar is viridis at one half.
    let bar = px(2 * (2 * 288 + 2) + 288, 2 * 186 + 4);
    let half = lightrig_imaging::figure::viridis(0.5);
    assert!(bar.iter().zip(half).all(|(a, b)| (a - b).abs() < 0.01), "{bar:?} {half:?}");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("![relit truth, fit, relative error](fit/relit-figure.png)"));
    // The detail texture (section 6.3) against the skin: T(x)/Π T(v_i)^b_i, everywhere observed
    // within one medium and on the lines; most of the lines' depth recovered (the camera's
    // 0.44 mm pixels blur the 0.8 mm lines).
    let d = r.detail;
    assert!(d.texels > 10_000 && d.lines > 400, "{d:?}");
    assert!(d.error.iter().all(|&e| e < 0.03), "{d:?}");
    assert!(d.lines_error.iter().all(|&e| e <= DETAIL_TOLERANCE), "{d:?}");
    assert!(d.depth.iter().all(|&x| x > 0.7 && x < 1.1), "{d:?}");
    assert_eq!(f.detail_vertices.len(), f.mesh.vertices.len());
    // The local term: the kernels' rates and totals on homogeneous marble against the dipole's
    // (also a target above), and a correction within 12 % of 1 for 80 % of the texels (it holds
    // the skin's lines, a few percent of the surface, and what the pooled rates leave of each
    // spot's own shape).
    let k = r.kernels.expect("local kernels");
    // The skin's lines raise many spots' misfit over the limit: 65 kept at this seed, 36 on
    // marble clear of the lines, 23 whose data a line crosses.
    assert!(k.spots[0] > 25 && k.lined.0 > 15 && f.spots.len() > 50, "{:?} {}", k.spots, f.spots.len());
    assert!(k.worst() <= KERNEL_TOLERANCE, "{k:?}");
    // Each spot's rates fitted with its neighbours' (6 spots in the median): σ2 scatters by
    // 4.0 % (median absolute deviation) at this seed.
    assert!(k.pooled >= 3 && k.spread[1] < 0.08 && k.spread[0] < 0.05, "{k:?}");
    // The held-out spots' near field predicted by the local term (8.5 % at this seed).
    assert!(f.held_out.near_frames > 80 && f.held_out.near_rel_rms < 0.1, "{:?}", f.held_out);
    assert!(k.total.iter().all(|&t| t < 0.05), "{k:?}");
    let mut corr: Vec<f32> = f.local.correction.iter().flatten().flat_map(|c| *c).collect();
    corr.sort_by(f32::total_cmp);
    let (lo, hi) = (corr[corr.len() / 10], corr[corr.len() * 9 / 10]);
    assert!(lo > 0.88 && hi < 1.12, "correction deciles {lo} {hi}");
    assert!(
        f.local.params.iter().zip(&f.atlas.texels).all(|(p, t)| p.is_some() == t.is_some()),
        "every texel filled"
    );

    // F's file: the upper triangle, read back as the fit's matrix, exactly symmetric.
    let n = f.mesh.vertices.len();
    let fit_dir = out.join("fit");
    let back = read_matrix(&fit_dir, n).unwrap();
    assert_eq!(back, f.matrix.values);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit_dir.join("F.json")).unwrap()).unwrap();
    assert_eq!(json["format"], F_FORMAT);
    assert_eq!(json["vertices"], n);
    let atlas: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit_dir.join("atlas.json")).unwrap()).unwrap();
    assert_eq!(atlas["format"], ATLAS_FORMAT);
    assert_eq!(atlas["triangle_chart"].as_array().unwrap().len(), f.mesh.triangles.len());
    let rates = lightrig_imaging::io::read(fit_dir.join("kernel-rates.exr")).unwrap();
    assert_eq!((rates.width, rates.height), (f.atlas.width, f.atlas.height));
    // The detail texture's file holds T_ρ at the atlas's texels.
    let detail = lightrig_imaging::io::read(fit_dir.join("detail.exr")).unwrap();
    assert_eq!((detail.width, detail.height), (f.atlas.width, f.atlas.height));
    let t = (0..f.atlas.texels.len()).find(|&i| f.detail.observed[i]).unwrap();
    assert_eq!(detail.data[3 * t..3 * t + 3], f.detail.values[t]);
    for file in [
        "object.ply",
        "relit.exr",
        "relit.png",
        "relit-global.png",
        "relit-truth.png",
        "fit.json",
        "kernel-c1.exr",
        "kernel-c2.exr",
        "kernel-correction.exr",
        "detail.exr",
    ] {
        assert!(fit_dir.join(file).is_file(), "{file}");
    }
    // Every fitted spot in fit.json, kept or not, with its rates as the fit has them.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit_dir.join("fit.json")).unwrap()).unwrap();
    assert_eq!(summary["glint_frames"].as_u64(), Some(f.glint_frames as u64));
    let listed = summary["local"]["spots"].as_array().unwrap();
    assert_eq!(listed.len(), f.spots.len() + f.local_rejected.len());
    assert_eq!(listed.iter().filter(|s| s["kept"] == true).count(), f.spots.len());
    assert_eq!(listed[0]["sigma_per_mm"][1].as_f64(), Some(f.spots[0].profile.sigma[1]));
    assert!(listed.iter().all(|s| s["incidence_deg"].as_f64().unwrap() <= f.local_params.max_incidence_deg));
    let bits = std::fs::read(fit_dir.join("F-observed.bits")).unwrap();
    assert_eq!(bits.len(), (n * (n + 1) / 2).div_ceil(8));
    let set: u32 = bits.iter().map(|b| b.count_ones()).sum();
    let upper =
        (0..n).flat_map(|k| (k..n).map(move |r| (r, k))).filter(|&(r, k)| f.observed[k * n + r]).count();
    assert_eq!(set as usize, upper);

    // Bad input, each refused with what and what to do, nothing written.
    let session = out.join("session");
    let none = |_: u64, _: u64| {};
    let e = fit_session(&session, Some(&out.join("nowhere.ply")), &none).unwrap_err().0;
    assert!(e.contains("nowhere.ply") && e.contains("--mesh"), "{e}");
    let e = fit_session(&out, None, &none).unwrap_err().0;
    assert!(e.contains("manifest") || e.contains("session"), "not a session: {e}");
    // Another object's mesh (the pebble a third larger): no pose matches its silhouettes.
    let scan = lightrig_host::mesh_file::read_mesh(&out.join("object.ply")).unwrap().mesh;
    let big = lightrig_pipelines::firs::mesh::Mesh {
        vertices: scan.vertices.iter().map(|v| v.map(|x| 1.3 * x)).collect(),
        triangles: scan.triangles.clone(),
    };
    let big_ply = out.join("big.ply");
    lightrig_pipelines::firs::mesh::write_ply(&big, &mut std::fs::File::create(&big_ply).unwrap()).unwrap();
    let e = fit_session(&session, Some(&big_ply), &none).unwrap_err().0;
    assert!(e.contains("big.ply") && e.contains("does not match") && e.contains("in mm"), "{e}");
    // The scan in a scanner's frame far from how the object stands (turned 119° about a tilted
    // axis and 25 mm aside): placed from the views' visual hull, every vertex where the
    // registration of the near scan put one (the pebble is symmetric under a half turn about its
    // axis, so the nearest placed vertex is compared), and F measured from as many frames.
    use lightrig_pipelines::disco::register::Pose;
    use lightrig_pipelines::vec3::{add, norm, scale, sub};
    let c = scale(scan.vertices.iter().fold([0.0; 3], |s, &v| add(s, v)), 1.0 / scan.vertices.len() as f64);
    let turn = Pose { rotation: [1.5, -1.2, 0.8], translation: [0.0; 3] };
    let far = Pose { translation: add(sub(c, turn.apply(c)), [20.0, -15.0, 0.0]), ..turn }.place(&scan);
    // Written as a scanner's tool might: OBJ, in metres, with a normal per vertex and the
    // surface in two groups. Unscaled it is refused with the unit to give; given it, fitted.
    let mut obj = String::from("# scanner export\nmtllib scan.mtl\no pebble\n");
    for v in &far.vertices {
        obj += &format!("v {:.12} {:.12} {:.12}\nvn 0 0 1\n", v[0] / 1e3, v[1] / 1e3, v[2] / 1e3);
    }
    for (k, t) in far.triangles.iter().enumerate() {
        if k == far.triangles.len() / 2 {
            obj += "g lower\n";
        }
        obj += &format!("f {0}//{0} {1}//{1} {2}//{2}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    let far_obj = out.join("far.obj");
    std::fs::write(&far_obj, obj).unwrap();
    let e = fit_session(&session, Some(&far_obj), &none).unwrap_err().0;
    assert!(e.contains("far.obj") && e.contains("across") && e.contains("--set plan.fit.mesh_unit=m"), "{e}");
    let metres: lightrig_host::overrides::Override = "plan.fit.mesh_unit=m".parse().unwrap();
    let placed =
        lightrig_host::fit::with_overrides(&[metres], || fit_session(&session, Some(&far_obj), &none))
            .unwrap()
            .unwrap();
    assert_eq!(placed.scan.format, lightrig_host::mesh_file::MeshFormat::Obj);
    assert_eq!((placed.scan.unit_mm, placed.scan.check.vertices), (1000.0, far.vertices.len()));
    assert!(
        placed.registration.as_ref().is_some_and(|g| g.from_hull && g.min_iou() > 0.995),
        "{:?}",
        placed.registration
    );
    let off = placed
        .mesh
        .vertices
        .iter()
        .map(|&p| f.mesh.vertices.iter().map(|&q| norm(sub(p, q))).fold(f64::MAX, f64::min))
        .fold(0.0, f64::max);
    assert!(off < REGISTRATION_TOLERANCE_MM, "a placed vertex {off} mm from the near scan's");
    assert!(
        placed.used.abs_diff(f.used) < f.used / 50,
        "{} frames resampled against {}",
        placed.used,
        f.used
    );
    // A registration frame with nothing in it (the spotlights failed): named, with what to check.
    let (s, _) = lightrig_host::session::Session::read(&session).unwrap();
    let first_view = s.frame_index().into_iter().nth(3).unwrap();
    let path = session.join(&first_view.file);
    let kept = std::fs::read(&path).unwrap();
    let dark = lightrig_imaging::io::Image::new(288, 186, 1);
    lightrig_imaging::io::write_exr(&path, &dark, lightrig_imaging::io::ExrPrecision::Float).unwrap();
    let e = fit_session(&session, None, &none).unwrap_err().0;
    assert!(e.contains(&first_view.file) && e.contains("registration frame shows no object"), "{e}");
    std::fs::write(&path, kept).unwrap();
    // The rig file's projector measured by hand, 5.6 mm and 0.6° from where it stood: entry
    // points 4 mm off. The fit finds it from the spots, and F is measured as well as before.
    let manifest = session.join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    let (s0, _) = lightrig_host::session::Session::read(&session).unwrap();
    let rig = lightrig_host::rigfile::RigFile::parse(&s0.manifest().rig, &manifest).unwrap();
    let truth = lightrig_host::disco::DiscoSetup::from_rig(&rig).unwrap().projector;
    let aimed = "eye_mm = [260, -150, 60], look_at_mm = [0, 0, 30]";
    let off = text.replace(aimed, "eye_mm = [263, -152.5, 64], look_at_mm = [0, 3, 27]");
    assert_ne!(off, text, "the manifest holds the rig file's projector");
    std::fs::write(&manifest, off).unwrap();
    let moved = fit_session(&session, None, &none).unwrap();
    std::fs::write(&manifest, &text).unwrap();
    let mp = &moved.projector;
    assert!(mp.shift_mm > 3.0 && mp.moved_mm > 4.0, "{mp:?}");
    let e = projector_error(&truth, &f.mesh, &mp.projector);
    assert!(e <= PROJECTOR_TOLERANCE_MM, "{e} mm from the true projector: {mp:?}");
    // Its spots chosen again by the projector it fitted: where it started hardly matters (the
    // two fits' entry points 0.025 mm apart at this seed; 0.100 mm from the true ones).
    let apart = projector_error(&f.projector.projector, &f.mesh, &mp.projector);
    assert!(
        apart < 0.05,
        "{apart} mm between the fits from the rig file's projector and from one 5.6 mm off"
    );
    assert!(moved.used.abs_diff(f.used) < f.used / 50, "{} frames resampled against {}", moved.used, f.used);
    // A rig file whose projector is aimed 40 mm beside where it stands: no spot where it says.
    let edited = text.replace(aimed, "eye_mm = [260, -150, 60], look_at_mm = [0, 40, 30]");
    assert_ne!(edited, text, "the manifest holds the rig file's projector");
    std::fs::write(&manifest, edited).unwrap();
    let e = fit_session(&session, None, &none).unwrap_err().0;
    assert!(e.contains("laser projector's pose") && e.contains("[plan.fit] projector"), "{e}");
    std::fs::write(&manifest, text).unwrap();
    // A frame of the wrong size (a camera ROI changed mid-run): named, with the sizes.
    let frame = s.frame_index().into_iter().nth(10).unwrap();
    let kept_frame = std::fs::read(session.join(&frame.file)).unwrap();
    let small = lightrig_imaging::io::Image::new(64, 32, 1);
    lightrig_imaging::io::write_exr(
        session.join(&frame.file),
        &small,
        lightrig_imaging::io::ExrPrecision::Float,
    )
    .unwrap();
    let e = fit_session(&session, None, &none).unwrap_err().0;
    assert!(e.contains(&frame.file) && e.contains("64 × 32") && e.contains("288 × 186"), "{e}");
    std::fs::write(session.join(&frame.file), kept_frame).unwrap();
    kept_demo::finish(&out);
}

#[test]
fn a_session_of_another_rig_is_refused() {
    use lightrig_host::acquire::plan_summary;
    use lightrig_host::plan::from_rig;
    use lightrig_host::rigfile::RigFile;
    use lightrig_host::session::{Manifest, Session};
    let dir = std::env::temp_dir().join(format!("lightrig-disco-other-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/lls-gantry.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let rig = RigFile::parse(&text, &path).unwrap();
    let info = lightrig_firmware::sim::virtual_device_info();
    let plan = from_rig::plan(&rig, &info).unwrap();
    Session::create(&dir, Manifest::new(text, &info, plan_summary(&plan))).unwrap();
    let e = fit_session(&dir, None, &|_, _| {}).unwrap_err().0;
    assert!(e.contains("linear-light-source") && e.contains("DISCO sessions"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A view whose registration frame is missing is refused, naming the step and what to do: here
/// the session took it under the blue laser and its rig file (as if edited after) now names the
/// spotlights, so no view has a frame with the spotlights alone on.
#[test]
fn a_view_without_its_registration_frame_is_refused() {
    let out = std::env::temp_dir().join(format!("lightrig-disco-noreg-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let opts = DiscoDemoOptions { quick: true, out: out.clone(), seed: 1, progress: false, real_time: false };
    let sets = ["plan.views=1", "plan.spot_grid=[2, 2]", "plan.registration=\"blue\""];
    acquire_disco(&opts, &sets.map(String::from)).unwrap();
    let manifest = out.join("session").join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    let edited = text.replace("registration = \\\"blue\\\"", "registration = \\\"spotlights\\\"");
    assert_ne!(edited, text, "the manifest holds the rig file's text");
    std::fs::write(&manifest, edited).unwrap();
    let e = fit_session(&out.join("session"), None, &|_, _| {}).unwrap_err().0;
    assert!(
        e.contains("step 1") && e.contains("has no registration frame") && e.contains("re-acquire"),
        "{e}"
    );
    std::fs::remove_dir_all(&out).ok();
}
