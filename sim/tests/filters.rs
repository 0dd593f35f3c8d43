//! The bispectral rig's tunable filters driven by the host over serial ports: simulated
//! filters on pseudo-terminals, tuned before each step through `FilterPreparation`; a filter
//! that refuses or never answers stops the run before the step starts, saying which and why.

use std::path::Path;
use std::time::Duration;

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::acquire::{self, plan_summary, AcquireError, Captured, FrameInput, Unattended};
use lightrig_host::bringup::bring_up_on;
use lightrig_host::filter::{self, FilterPreparation};
use lightrig_host::plan::{from_rig, Step};
use lightrig_host::rigfile::RigFile;
use lightrig_host::session::{Manifest, Session};
use lightrig_host::transport::Transport;
use lightrig_protocol::event::TriggerEvent;
use lightrig_sim::filter::PtyFilter;
use lightrig_sim::transport::connect_for_camera;

/// One small frame per trigger.
#[derive(Default)]
struct Frames(Vec<Captured>);

impl FrameInput for Frames {
    fn begin_step(&mut self, _: &Step) -> std::io::Result<()> {
        Ok(())
    }
    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        let data = format!("frame {}\n", t.frame).into_bytes();
        let host_us = host_us.unwrap_or(0.0) + 100.0;
        self.0.push(Captured {
            camera: t.camera,
            frame: Some(t.frame),
            ext: "txt".into(),
            data,
            host_us,
            before_step: false,
            stamp: None,
        });
        Ok(())
    }
    fn poll(&mut self, _: f64) -> std::io::Result<Vec<Captured>> {
        Ok(std::mem::take(&mut self.0))
    }
}

/// The shipped bispectral rig, two sample angles, one light angle, two wavelength pairs, its
/// filters on `light` and `camera`.
fn rig(light: &Path, camera: &Path) -> RigFile {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/rigs/bispectral.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[plan.tunable_filter]", "pairs = [[380, 450], [400, 600]]\n[plan.tunable_filter]")
        .replace("settle_ms = 50", &format!(
            "settle_ms = 0\nlight_range_nm = [350, 720]\nlight_port = \"{}\"\ncamera_port = \"{}\"\ntimeout_ms = 500",
            light.display(),
            camera.display()
        ))
        .replace("sample_angles = [0]", "sample_angles = [0, 30]")
        .replace(
            "light_angles = [0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130, 140, 150]",
            "light_angles = [60]",
        );
    RigFile::parse(&text, &path).unwrap()
}

fn run(rig: &RigFile, name: &str) -> (Result<(), AcquireError>, std::path::PathBuf) {
    let dir = std::env::temp_dir().join(format!("lightrig-filters-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let info = virtual_device_info();
    let plan = from_rig::plan(rig, &info).unwrap();
    let (transport, _) = connect_for_camera(rig, info, false);
    let transport: Box<dyn Transport> = Box::new(transport);
    let mut client = bring_up_on(rig, transport).unwrap();
    let mut session =
        Session::create(&dir, Manifest::new("# bispectral", client.info(), plan_summary(&plan))).unwrap();
    let filters = filter::from_rig(rig).unwrap();
    assert_eq!(filters.len(), 2);
    let mut prep = FilterPreparation { filters, rest: Box::new(Unattended("virtual")) };
    let r =
        acquire::run_prepared(&mut client, &mut session, &plan, &mut Frames::default(), &mut prep, |_| {});
    (r, dir)
}

#[test]
fn each_step_tunes_both_filters_before_it_runs() {
    let settle = Duration::from_millis(5);
    let light = PtyFilter::start((350.0, 720.0), settle, false).unwrap();
    let camera = PtyFilter::start((400.0, 720.0), settle, false).unwrap();
    let rig = rig(light.path(), camera.path());
    let (r, dir) = run(&rig, "ok");
    r.unwrap();
    // Two geometries × two pairs, in plan order.
    assert_eq!(light.tuned(), [380.0, 400.0, 380.0, 400.0]);
    assert_eq!(camera.tuned(), [450.0, 600.0, 450.0, 600.0]);
    let by = lightrig_host::session::prepared_by(&dir).unwrap();
    assert_eq!(by, ["instruments"; 4]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_refusing_or_silent_filter_stops_the_run_before_the_step_and_says_so() {
    let settle = Duration::from_millis(1);
    let light = PtyFilter::start((350.0, 720.0), settle, false).unwrap();
    // This camera filter covers less than the rig file says: it refuses 450 nm.
    let camera = PtyFilter::start((500.0, 720.0), settle, false).unwrap();
    let (r, dir) = run(&rig(light.path(), camera.path()), "refused");
    let e = r.unwrap_err().to_string();
    assert!(e.contains("camera filter: refused 450 nm") && e.contains("out of range"), "{e}");
    assert!(e.contains("`lightrig resume` continues from it"), "{e}");
    let (s, _) = Session::read(&dir).unwrap();
    assert!(s.frame_index().is_empty() && s.open_attempt().is_none(), "nothing of the step started");
    std::fs::remove_dir_all(&dir).unwrap();
    let silent = PtyFilter::start((350.0, 720.0), settle, true).unwrap();
    let (r, dir) = run(&rig(silent.path(), camera.path()), "silent");
    let e = r.unwrap_err().to_string();
    assert!(e.contains("light filter: no answer to 380 nm in time"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
