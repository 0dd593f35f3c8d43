//! The BRDF display end to end through the command line's pieces: the quick demo (calibration,
//! a sweep of Ward roughnesses, the closed loop, on the scene with every fault on and with
//! each alone) against the scene's truth, and the planner's refusal of an α the calibrated
//! display cannot reach.

mod kept_demo;

use lightrig_cli::demo::display::{run_display, DisplayDemoOptions};
use lightrig_host::plan::from_rig;
use lightrig_host::rigfile::RigFile;

#[test]
fn the_quick_display_demo_meets_its_targets_and_refuses_what_it_cannot_show() {
    let out = kept_demo::out_dir("display", "lightrig-display-demo");
    let opts =
        DisplayDemoOptions { quick: true, out: out.clone(), seed: 1, progress: false, real_time: false };
    let r = run_display(&opts).unwrap();
    for (name, value, limit, met) in r.targets() {
        assert!(met, "{name}: {value} against {limit}");
    }
    // The sweep covers the thesis's range, both axes, and 3:1 either way.
    let targets: Vec<[f64; 2]> = r.first.iter().map(|s| s.target).collect();
    assert!(targets.contains(&[0.02, 0.02]) && targets.contains(&[0.14, 0.14]));
    assert!(targets.contains(&[0.12, 0.04]) && targets.contains(&[0.03, 0.09]));
    // The loop closed: every axis of every target nearer its goal the second time, or already
    // within 0.2 %.
    for (a, b) in r.first.iter().zip(&r.corrected) {
        for k in 0..2 {
            let (e1, e2) = (a.error()[k].abs(), b.error()[k].abs());
            assert!(e2 < e1 || e2 < 0.002, "{:?} axis {k}: {e1} then {e2}", a.target);
        }
    }
    // The same workflow on each fault alone and on the ideal display: each within the
    // targets too, and the report says what each did.
    let names: Vec<&str> = r.faults.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["none", "film", "walls", "harmonics", "crosstalk"]);
    for f in &r.faults {
        assert!(f.response_error < 0.05 && f.first < 0.05 && f.corrected < 0.01, "{f:?}");
    }
    let report = std::fs::read_to_string(&r.report).unwrap();
    for f in &r.faults {
        let row = format!("| {} | {:.2} % | {:.2} % |", f.name, 100.0 * f.response_error, 100.0 * f.first);
        assert!(report.contains(&row), "{row}");
    }
    for heading in [
        "## Calibration",
        "## After calibration",
        "## After one correction",
        "## What each fault does",
        "figure 5.8",
    ] {
        assert!(report.contains(heading), "{heading}");
    }
    // The slope histograms as pictures, linked from the report and its HTML page: one sine
    // against Eq. 5.6, then 1, 3, 5 and 7 partials against a Gaussian; 40 bins of 6 px.
    let html = std::fs::read_to_string(r.report.with_extension("html")).unwrap();
    let names: Vec<&str> = r.histograms.iter().map(|(f, _)| f.as_str()).collect();
    assert_eq!(
        names,
        [
            "slopes-one-sine.png",
            "slopes-1-partials.png",
            "slopes-3-partials.png",
            "slopes-5-partials.png",
            "slopes-7-partials.png"
        ]
    );
    // The highlights after the correction, one 192 × 192 panel per target, a pixel apart.
    let (file, caption) = &r.lobes;
    assert!(report.contains(&format!("![{caption}]({file})")) && html.contains("<img src=\"lobes.png\""));
    let lobes = lightrig_imaging::io::read(out.join(file)).unwrap();
    let n = r.corrected.len() as u32;
    assert_eq!((lobes.width, lobes.height), (192 * n + (n - 1), 192 + 3), "{caption}");
    for (file, caption) in &r.histograms {
        assert!(report.contains(&format!("![{caption}]({file})")), "{file}");
        assert!(html.contains(&format!("<img src=\"{file}\"")), "{file}");
        let img = lightrig_imaging::io::read(out.join(file)).unwrap();
        assert_eq!((img.width, img.height), (240, 160), "{file}");
    }
    // A rig file asking for more than the calibrated coils reach is refused, with the range.
    let shipped = include_str!("../../docs/rigs/brdf-display.toml");
    let text = shipped.replacen(
        "[plan.calibrate]\ndrive = 0.03",
        "alphas = [[0.08, 0.04], [0.3, 0.05]]\ncalibration = \"calibration/display-calibration.json\"\n",
        1,
    );
    let path = out.join("too-rough.toml");
    std::fs::write(&path, &text).unwrap();
    let rig = RigFile::parse(&text, &path).unwrap();
    let e = from_rig::plan(&rig, &lightrig_firmware::sim::virtual_device_info()).unwrap_err().to_string();
    assert!(e.contains("too-rough.toml") && e.contains("plan.alphas"), "{e}");
    assert!(e.contains("αx = 0.3 cannot be shown: this display reaches 0 < αx ≤ 0.158"), "{e}");
    // `lightrig display` on that rig: live changes from standard input, refusals with the
    // range, a fade at the end; an unreachable α on the command line is a usage error.
    let live = |alpha: &str, input: &str| {
        use std::io::Write;
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_lightrig"))
            .args(["display", path.to_str().unwrap(), "--alpha", alpha, "--ramp-ms", "50"])
            .stdin(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        child.stdin.take().unwrap().write_all(input.as_bytes()).unwrap();
        let o = child.wait_with_output().unwrap();
        (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (code, said) = live("0.08,0.04", "0.05\n0.3,0.02\n");
    assert_eq!(code, Some(0), "{said}");
    for line in [
        "showing αx = 0.08, αy = 0.04",
        "showing αx = 0.05, αy = 0.05",
        "refused: αx = 0.3 cannot be shown",
        "faded to silence",
    ] {
        assert!(said.contains(line), "{line}: {said}");
    }
    // The largest α the display reports, asked for exactly: its quantised drives stay within
    // the coils' limit, so the controller takes them.
    let max = said.split("0 < αx ≤ ").nth(1).and_then(|r| r.split(' ').next()).unwrap().to_string();
    let (code, said2) = live(&max, "");
    assert_eq!(code, Some(0), "{said2}");
    let (code, said) = live("0.3", "");
    assert_eq!(code, Some(2), "{said}");
    assert!(said.contains("this display reaches 0 < αx ≤ 0.158"), "{said}");
    kept_demo::finish(&out);
}
