//! Plans made from the example rig files: counts and device units.

use std::path::PathBuf;

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::plan::from_rig;
use lightrig_host::rigfile::RigFile;
use lightrig_protocol::sequence::Action;

fn example(name: &str) -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/rigs")).join(name)
}

#[test]
fn the_gantry_example_plans_one_bracket_per_half_millimetre() {
    let rig = RigFile::load(&example("lls-gantry.toml")).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    // The board frame (its bracket), then -180..=180 mm every 0.5 mm = 721 positions;
    // 3 exposures; light tube and stripe passes.
    let s = plan.summary();
    assert_eq!((s.steps, s.triggers), (3, 3 + 721 * 3 * 2));
    assert_eq!(plan.steps[0].meta["pass"], "board");
    let moves: Vec<i32> = plan.steps[1]
        .items()
        .iter()
        .filter_map(|i| match i.action {
            Action::StepperMove { target, .. } => Some(target),
            _ => None,
        })
        .collect();
    // 80 steps/mm: the first move goes to the start, then every 40 steps.
    assert_eq!(&moves[..3], [-14_400, -14_400, -14_360]);
    assert_eq!(*moves.last().unwrap(), 14_400);
    let widths: Vec<u32> = plan.steps[1]
        .items()
        .iter()
        .filter_map(|i| match i.action {
            Action::Trigger { exposure, .. } => Some(exposure),
            _ => None,
        })
        .take(3)
        .collect();
    assert_eq!(widths, [500, 2_000, 8_000]);
    assert_eq!(plan.steps[2].meta["pass"], "stripe");
}

#[test]
fn a_small_disco_rig_plans_views_lasers_and_spots() {
    let text = std::fs::read_to_string(example("disco.toml")).unwrap();
    let text = text.replace("views = 72", "views = 4").replace("spot_grid = [64, 64]", "spot_grid = [3, 2]");
    let rig = RigFile::parse(&text, &example("disco.toml")).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    // The white balance, then 4 views at each of the 2 camera positions: a registration frame
    // and 6 spots × 3 lasers each.
    assert_eq!(plan.summary().steps, 1 + 2 * 4);
    assert_eq!(plan.summary().triggers, 3 + 2 * 4 * (1 + 3 * 6));
    // The spots span `spot_window_deg` (±5.5° × ±6.5° optical) about the zero codes.
    let g = &plan.meta["grid"];
    let code = |deg: f64| (32768.0 + deg.to_radians() * 1e6 / 10.6526).round() as i64;
    assert_eq!(g[0][0].as_i64().unwrap(), code(-5.5));
    assert_eq!(g[2][0].as_i64().unwrap(), code(5.5));
    assert_eq!(g[0][1].as_i64().unwrap(), code(6.5) - 2 * (code(6.5) - 32768), "y is mirrored");
    assert_eq!(plan.steps[0].meta["kind"], "white");
    assert_eq!(plan.steps[5].meta["camera_position"], 1);
    assert!(plan.steps[5].meta["operator"].as_str().unwrap().contains("`left`"));
    // A window beyond the galvo's range is refused, naming the key.
    let wide = text.replace(
        "spot_window_deg = [[-5.5, 5.5], [-6.5, 6.5]]",
        "spot_window_deg = [[-25, 25], [-6.5, 6.5]]",
    );
    let rig = RigFile::parse(&wide, &example("disco.toml")).unwrap();
    let e = from_rig::plan(&rig, &virtual_device_info()).unwrap_err().to_string();
    assert!(e.contains("plan.spot_window_deg") && e.contains("outside the galvo"), "{e}");
}

#[test]
fn plan_mistakes_point_at_the_rig_file() {
    let path = example("lls-gantry.toml");
    let text = std::fs::read_to_string(&path).unwrap().replace("step_mm = 0.5", "step_mm = -1");
    let rig = RigFile::parse(&text, &path).unwrap();
    let Err(e) = from_rig::plan(&rig, &virtual_device_info()) else { panic!("planned") };
    let e = e.to_string();
    assert!(e.contains("lls-gantry.toml:") && e.contains("plan.step_mm: must be positive"), "{e}");
    let text =
        std::fs::read_to_string(&path).unwrap().replace("pass_mm = [-180, 180]", "pass_mm = [-180, 900]");
    let rig = RigFile::parse(&text, &path).unwrap();
    let Err(e) = from_rig::plan(&rig, &virtual_device_info()) else { panic!("planned beyond the limits") };
    let e = e.to_string();
    assert!(e.contains("plan.pass_mm") && e.contains("200"), "beyond the soft limits: {e}");
}

#[test]
fn lost_frame_retries_default_to_two_and_are_read_from_the_plan_table() {
    let path = example("lls-gantry.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let with = |line: &str| text.replace("step_mm = 0.5", &format!("step_mm = 0.5\n{line}"));
    let plan = |t: &str| from_rig::plan(&RigFile::parse(t, &path).unwrap(), &virtual_device_info());
    assert_eq!(plan(&text).unwrap().lost_retries, 2);
    assert_eq!(plan(&with("lost_frame_retries = 0")).unwrap().lost_retries, 0);
    assert_eq!(plan(&with("lost_frame_retries = 5")).unwrap().lost_retries, 5);
    let Err(e) = plan(&with("lost_frame_retries = 1.5")) else { panic!("planned") };
    let e = e.to_string();
    assert!(
        e.contains("lls-gantry.toml:") && e.contains("plan.lost_frame_retries: 1.5 is not a whole number"),
        "{e}"
    );
}

#[test]
fn the_immersion_and_display_examples_plan() {
    let rig = RigFile::load(&example("fluorescent-immersion.toml")).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    // Calibration at two target positions (a board frame, a dark frame and a sweep each), then
    // 36 orientations of 365 sheets over the sweep's codes.
    assert_eq!(plan.summary().steps, 2 * 2 + 36);
    assert_eq!(plan.summary().triggers, 2 * (1 + 1 + 365) + 36 * 365);
    let codes: Vec<u16> = plan.steps[4]
        .items()
        .iter()
        .filter_map(|i| match &i.action {
            Action::GalvoPoint { to, .. } => Some(to.x),
            _ => None,
        })
        .collect();
    assert_eq!((codes.first(), codes.last()), (Some(&31578), Some(&33749)), "the sweep spans sweep_codes");
    // The display ships as its calibration: a still surface, then one sine per coil per step.
    let path = example("brdf-display.toml");
    let rig = RigFile::load(&path).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    assert_eq!(plan.steps.len(), 1 + 49, "the still surface and the 49 frequencies of the sweep");
    let sounding = |step: usize| -> Vec<(u8, Vec<u32>)> {
        plan.steps[step]
            .items()
            .iter()
            .filter_map(|i| match &i.action {
                Action::VoiceCoil { channel, partials, .. } if !partials.is_empty() => {
                    Some((*channel, partials.iter().map(|p| p.freq_mhz).collect()))
                }
                _ => None,
            })
            .collect()
    };
    assert_eq!(sounding(0), vec![], "the still surface");
    assert_eq!(
        sounding(1),
        vec![(0, vec![90_000]), (1, vec![100_000])],
        "one sine per coil, the sweep's first"
    );
    assert_eq!(sounding(49), vec![(0, vec![330_000]), (1, vec![340_000])], "5 Hz apart, to the last");
    assert_eq!(plan.steps[1].meta["kind"], "sine");
    assert_eq!(plan.meta["liquid"], "water");
    // Raw patterns instead: every coil gets each pattern.
    let text = std::fs::read_to_string(&path).unwrap().replace(
        "[plan.calibrate]\ndrive = 0.03",
        "[plan.patterns]\nglossy = { frequencies_hz = [40, 55, 70], amplitudes = [0.2, 0.15, 0.1] }\n#",
    );
    let rig = RigFile::parse(&text, &path).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    assert_eq!(plan.steps.len(), 1, "one step per pattern");
    let coils = plan.steps[0]
        .items()
        .iter()
        .filter(|i| matches!(i.action, Action::VoiceCoil { ref partials, .. } if !partials.is_empty()))
        .count();
    assert_eq!(coils, rig.voice_coils.len(), "every coil gets the pattern");
    // Both, or neither: the planner says what it takes.
    let both = text.replace("[plan.patterns]", "alphas = [[0.1, 0.1]]\n[plan.patterns]");
    let rig = RigFile::parse(&both, &path).unwrap();
    let e = from_rig::plan(&rig, &virtual_device_info()).unwrap_err().to_string();
    assert!(e.contains("give exactly one of `[plan.calibrate]`"), "{e}");
    // α without a calibration file: what to run to make one.
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[plan.calibrate]\ndrive = 0.03", "alphas = [[0.1, 0.1]]");
    let rig = RigFile::parse(&text, &path).unwrap();
    let e = from_rig::plan(&rig, &virtual_device_info()).unwrap_err().to_string();
    assert!(e.contains("plan.calibration") && e.contains("lightrig fit display"), "{e}");
}

#[test]
fn the_bispectral_example_plans_every_pair_above_the_diagonal() {
    let path = example("bispectral.toml");
    let rig = RigFile::load(&path).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    // LEDs 380..460 nm and the xenon through the light filter 480..720 nm excite; the camera's
    // tunable filter covers 400..=720 nm in 20 nm steps: emissions at or above each excitation
    // (the thesis's 170 pairs), at 16 light angles.
    let excitations: Vec<u32> =
        [380u32, 400, 420, 440, 460].into_iter().chain((480..=720).step_by(20)).collect();
    let per_geometry: usize =
        excitations.iter().map(|&ex| (400..=720).step_by(20).filter(|&em| em >= ex).count()).sum();
    assert_eq!(per_geometry, 170);
    assert_eq!(plan.summary().steps, 16 * per_geometry);
    assert_eq!(plan.steps[0].meta["host"]["camera_filter_nm"], 400);
    // The xenon's pairs go through the wheel's `white` slot.
    let white = plan.steps.iter().find(|s| s.meta["excitation_nm"] == 500).unwrap();
    assert_eq!(white.meta["slot"], 6);
    // Sparse mode: only the chosen pairs, an LED's and the xenon's.
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[plan.tunable_filter]", "pairs = [[380, 460], [500, 600]]\n[plan.tunable_filter]");
    let rig = RigFile::parse(&text, &path).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    assert_eq!(plan.summary().steps, 16 * 2);
    // A pair the filters cannot reach is a rig-file error naming it.
    for (pairs, says) in
        [("[[400, 750]]", "camera filter reaches 400-720 nm"), ("[[390, 520]]", "nothing excites at 390 nm")]
    {
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("[plan.tunable_filter]", &format!("pairs = {pairs}\n[plan.tunable_filter]"));
        let rig = RigFile::parse(&text, &path).unwrap();
        let e = from_rig::plan(&rig, &virtual_device_info()).unwrap_err().to_string();
        assert!(e.contains("plan.pairs") && e.contains(says), "{e}");
    }
    // The Spectralon session: each excitation's row within two bands of its diagonal.
    let text =
        std::fs::read_to_string(&path).unwrap().replace("sample = \"spheres\"", "sample = \"spectralon\"");
    let rig = RigFile::parse(&text, &path).unwrap();
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    let row: Vec<u64> = plan
        .steps
        .iter()
        .filter(|s| s.meta["geometry"] == 0 && s.meta["excitation_nm"] == 440)
        .map(|s| s.meta["emission_nm"].as_u64().unwrap())
        .collect();
    assert_eq!(row, [400, 420, 440, 460, 480]);
}

#[test]
fn plan_cameras_are_picked_by_name_or_index_and_mistakes_name_the_line() {
    let path = example("disco.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("views = 72", "views = 2")
        .replace("spot_grid = [64, 64]", "spot_grid = [2, 2]")
        .replace(
            "[plan]",
            "[[camera]]\ncamera = 2\nname = \"side\"\npulse_us = 300\nmin_interval_us = 90000\n\n[plan]",
        );
    let with = |key: &str| {
        let t = text.replace("views = 2", &format!("views = 2\n{key}"));
        RigFile::parse(&t, &path).unwrap()
    };
    let triggers_per_camera = |rig: &RigFile| {
        let plan = from_rig::plan(rig, &virtual_device_info()).unwrap();
        // Step 0 is the white balance; step 1 the first view.
        let items = plan.steps[1].items();
        let widths: Vec<(u8, u32)> = items
            .iter()
            .filter_map(|i| match i.action {
                Action::Trigger { camera, exposure } => Some((camera, exposure)),
                _ => None,
            })
            .take(2)
            .collect();
        (plan.steps[1].triggers.clone(), widths)
    };
    // Both cameras by default, fired together with the longer pulse (300 µs) as the exposure.
    let rig = RigFile::parse(&text, &path).unwrap();
    // A registration frame and 2 × 2 spots × 3 lasers per view.
    assert_eq!(triggers_per_camera(&rig), (vec![(0, 13), (2, 13)], vec![(0, 300), (2, 300)]));
    assert_eq!(triggers_per_camera(&with("cameras = [\"side\"]")).0, [(2, 13)]);
    assert_eq!(triggers_per_camera(&with("cameras = [2, \"hdr\"]")).0, [(2, 13), (0, 13)]);
    for (key, says) in [
        ("cameras = [\"top\"]", "no camera `top` (the rig has: hdr (0), side (2))"),
        ("cameras = [0, \"hdr\"]", "camera `hdr` is listed twice"),
        ("cameras = []", "is empty"),
        ("cameras = \"hdr\"", "must be a list of camera names or device indices"),
    ] {
        let e = from_rig::plan(&with(key), &virtual_device_info()).unwrap_err().to_string();
        assert!(e.contains("plan.cameras") && e.contains(says), "{key}: {e}");
        assert!(e.contains("disco.toml:"), "names the file and line: {e}");
    }
}

#[test]
fn a_pca_steered_bispectral_plan_takes_every_pair_at_its_dense_angles_and_decides_the_rest_when_reached() {
    use lightrig_host::steer::{Choice, CHOICE_FILE};
    let path = example("bispectral.toml");
    let steered = |extra: &str| {
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace(
                "light_angles = [0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130, 140, 150]",
                "light_angles = [0, 35, 70, 100, 140]",
            )
            .replace("[plan.gonio]", &format!("[plan.steer]\n{extra}\n\n[plan.gonio]"));
        RigFile::parse(&text, &path).unwrap()
    };
    let rig = steered("dense_angles = [0, 70, 140]\nselect = 5");
    let plan = from_rig::plan(&rig, &virtual_device_info()).unwrap();
    // Three dense angles × 170 pairs first, then two angles × 5 chosen pairs.
    assert_eq!(plan.steps.len(), 3 * 170 + 2 * 5);
    assert!(plan.steps[..510].iter().all(|s| s.meta["chosen"].is_null() && s.meta["excitation_nm"].is_u64()));
    let sparse = &plan.steps[510..];
    assert!(sparse.iter().all(|s| s.meta["excitation_nm"].is_null()));
    assert_eq!(
        sparse.iter().map(|s| s.meta["chosen"].as_u64().unwrap()).collect::<Vec<_>>(),
        [0, 1, 2, 3, 4, 0, 1, 2, 3, 4]
    );
    // Optical exposure: 520 steps' series against 5 × 170.
    let (planned, dense) = (
        plan.meta["optical_exposure_s"].as_f64().unwrap(),
        plan.meta["dense_optical_exposure_s"].as_f64().unwrap(),
    );
    assert!((planned / dense - 520.0 / 850.0).abs() < 1e-12, "{planned} / {dense}");
    // Reached in a session holding a choice, a sparse step becomes that pair's step: the same
    // triggers, the wavelengths in its meta, the wheel at the pair's slot.
    let dir = std::env::temp_dir().join(format!("lightrig-steer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let choice = Choice {
        pairs: vec![[400, 520], [500, 500], [440, 540], [600, 600], [700, 700]],
        from_light_deg: vec![0.0, 70.0, 140.0],
        cond: 2.0,
    };
    choice.save(&dir).unwrap();
    assert_eq!(Choice::load(&dir).unwrap(), Some(choice));
    let step = sparse[1].resolve(&dir).unwrap().expect("a steered step resolves");
    assert_eq!(
        (step.id, step.meta["excitation_nm"].as_u64(), step.meta["emission_nm"].as_u64()),
        (sparse[1].id, Some(500), Some(500))
    );
    assert_eq!(step.meta["chosen"], 1);
    assert_eq!(step.meta["host"]["light_filter_nm"], 500);
    let white = 6; // the wheel's `white` slot carries the xenon's 500 nm
    assert!(step
        .items()
        .iter()
        .any(|i| matches!(i.action, Action::FilterWheel { slot, .. } if slot == white)));
    assert_eq!(step.triggers, sparse[1].triggers);
    let led = sparse[0].resolve(&dir).unwrap().unwrap();
    assert!(
        led.items().iter().any(|i| matches!(i.action, Action::FilterWheel { slot: 2, .. })),
        "led-400 is slot 2"
    );
    assert!(plan.steps[0].resolve(&dir).unwrap().is_none(), "a dense step is what it is");
    // A choice naming a pair the plan does not take is refused, naming the file.
    Choice { pairs: vec![[390, 520]; 5], from_light_deg: vec![], cond: 1.0 }.save(&dir).unwrap();
    let e = sparse[0].resolve(&dir).unwrap_err();
    assert!(e.contains(CHOICE_FILE) && e.contains("390→520 nm"), "{e}");
    // Without a choice and without a Spectralon session named, the step says what is missing.
    std::fs::remove_file(dir.join(CHOICE_FILE)).unwrap();
    let e = sparse[0].resolve(&dir).unwrap_err();
    assert!(e.contains("[plan.fit] spectralon"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
    // A dense angle the gonio does not take is a rig-file error.
    let e = from_rig::plan(&steered("dense_angles = [0, 65]\nselect = 5"), &virtual_device_info())
        .unwrap_err()
        .to_string();
    assert!(e.contains("plan.steer.dense_angles") && e.contains("65"), "{e}");
}
