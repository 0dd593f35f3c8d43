//! `lightrig demo`: a whole acquisition and fit on the virtual rig, checked against the
//! ground truth the frames were rendered from. One module per rig ([`lls`], [`firs`]); what
//! they share is here: the demo's rig file written and planned ([`DemoRig`]), the acquisition
//! on the virtual rig exactly as `lightrig acquire` runs it ([`DemoRig::acquire`]), the
//! ground truth's scene file, progress bars and the report's tables ([`Report`]).

pub mod brrdf;
pub mod disco;
pub mod display;
pub mod firs;
pub mod lls;
pub mod lls_figures;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use indicatif::{ProgressBar, ProgressStyle};
use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::acquire::{self, plan_summary};
use lightrig_host::bringup::bring_up_on;
use lightrig_host::plan::{from_rig, Plan};
use lightrig_host::rigfile::RigFile;
use lightrig_host::session::{Manifest, Session};
use lightrig_host::transport::Transport;
use lightrig_protocol::session::DeviceInfo;
use lightrig_sim::camera::{Scene, VirtualCamera};
use lightrig_sim::sensor::Sensor;
use lightrig_sim::transport::connect_for_camera;

use crate::error::{err, failure, io, CliError, FAILURE, INPUT, USAGE};

/// Arguments of `lightrig demo`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Method: `lls` (linear light source), `firs` (fluorescent immersion), `display` (BRDF
    /// display), `brrdf` (bispectral) or `disco` (translucent objects).
    #[arg(default_value = "lls")]
    pub method: String,
    /// A small scene for a quick check (about half a minute).
    #[arg(long)]
    pub quick: bool,
    /// Output directory.
    #[arg(long, default_value = "lightrig-demo")]
    pub out: PathBuf,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Exit with failure if a fit accuracy target is missed.
    #[arg(long)]
    pub check: bool,
    /// Run the virtual rig in real time, as long as the real rig would take (by default
    /// simulated time jumps ahead whenever the device waits).
    #[arg(long)]
    pub real_time: bool,
    /// The LLS gantry's step, mm (default 1, 2 with --quick): 0.6 gives the 400-frame
    /// passes of the fit's benchmark (docs/benchmarks.md).
    #[arg(long)]
    pub step_mm: Option<f64>,
    /// The LLS demo's virtual camera applies this display gamma (1 = linear, the default):
    /// the demo then recovers the camera's response with `lightrig hdr calibrate`'s method from
    /// an exposure series, names it in the rig file, and the fit merges through it.
    #[arg(long)]
    pub camera_gamma: Option<f64>,
    /// Serve the acquisition's live page and API (docs/live-api.md) on ADDR, by default
    /// 127.0.0.1:7878 (`127.0.0.1:0`: any free port, printed at start).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = lightrig_serve::DEFAULT_ADDR)]
    pub serve: Option<String>,
    /// No progress bars (the Python package's `demo(progress=False)`).
    #[arg(skip)]
    pub quiet: bool,
    /// Stops the virtual device as Ctrl-C stops a real one (the Python package's
    /// `KeyboardInterrupt`): the acquisition under way ends with an emergency stop.
    #[arg(skip)]
    pub interrupt: Option<std::sync::Arc<lightrig_host::client::Interrupt>>,
}

/// What a demo run made.
#[derive(Debug, Clone)]
pub struct DemoRun {
    /// The accuracy targets missed (empty: every one met).
    pub missed: Vec<String>,
    /// Its `report.md`.
    pub report: PathBuf,
}

/// What every acquisition of the demo running on this thread shares: `--serve`'s address and
/// the caller's interrupt ([`run_demo`] sets them for its run).
#[derive(Default, Clone)]
struct Context {
    serve: Option<String>,
    interrupt: Option<std::sync::Arc<lightrig_host::client::Interrupt>>,
}

thread_local! {
    static CONTEXT: std::cell::RefCell<Context> = std::cell::RefCell::default();
}

/// Clears [`CONTEXT`] when the run ends, however it ends.
struct ContextGuard;

impl Drop for ContextGuard {
    fn drop(&mut self) {
        CONTEXT.with(|c| *c.borrow_mut() = Context::default());
    }
}

/// Runs `lightrig demo [METHOD]`: the demo's output in `out/<method>/`; with `check`, a
/// missed accuracy target is a failure.
pub fn run(args: &Args) -> ExitCode {
    match run_demo(args) {
        Ok(run) if args.check && !run.missed.is_empty() => {
            eprintln!("error: accuracy targets missed: {}", run.missed.join(", "));
            ExitCode::from(FAILURE)
        }
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", e.message);
            ExitCode::from(e.code)
        }
    }
}

/// [`run`]'s work: the demo of `args.method`, its report written; an error for arguments that do
/// not fit the method (exit code [`USAGE`]) or a demo that failed.
pub fn run_demo(args: &Args) -> Result<DemoRun, CliError> {
    CONTEXT
        .with(|c| *c.borrow_mut() = Context { serve: args.serve.clone(), interrupt: args.interrupt.clone() });
    let _context = ContextGuard;
    let progress = !args.quiet;
    let firs = args.method == "firs" || args.method == "fluorescent-immersion";
    if let Some(step) = args.step_mm.filter(|_| firs) {
        return Err(err(
            USAGE,
            format!("--step-mm {step}: the firs demo has no gantry; it is for `lightrig demo lls`"),
        ));
    }
    if let Some(step) = args.step_mm.filter(|s| !(0.1..=5.0).contains(s)) {
        return Err(err(USAGE, format!("--step-mm {step}: give a gantry step from 0.1 to 5 mm")));
    }
    let display = args.method == "display" || args.method == "brdf-display";
    let lls = args.method == "lls" || args.method == "linear-light-source";
    if let Some(g) = args.camera_gamma.filter(|_| !lls) {
        return Err(err(
            USAGE,
            format!("--camera-gamma {g}: only `lightrig demo lls` has a camera response to recover"),
        ));
    }
    if let Some(g) = args.camera_gamma.filter(|g| !(0.2..=5.0).contains(g)) {
        return Err(err(
            USAGE,
            format!("--camera-gamma {g}: give a gamma from 0.2 to 5 (1 is a linear camera)"),
        ));
    }
    if let Some(step) = args.step_mm.filter(|_| display) {
        return Err(err(
            USAGE,
            format!("--step-mm {step}: the display demo has no gantry; it is for `lightrig demo lls`"),
        ));
    }
    let brrdf = args.method == "brrdf" || args.method == "bispectral";
    if let Some(step) = args.step_mm.filter(|_| brrdf) {
        return Err(err(
            USAGE,
            format!("--step-mm {step}: the brrdf demo has no gantry; it is for `lightrig demo lls`"),
        ));
    }
    let disco = args.method == "disco";
    if let Some(step) = args.step_mm.filter(|_| disco) {
        return Err(err(
            USAGE,
            format!("--step-mm {step}: the disco demo has no gantry; it is for `lightrig demo lls`"),
        ));
    }
    if disco {
        let opts = disco::DiscoDemoOptions {
            quick: args.quick,
            out: args.out.join("disco"),
            seed: args.seed,
            progress,
            real_time: args.real_time,
        };
        disco::run_disco(&opts).map(|r| {
            eprintln!("report: {}", r.report.display());
            DemoRun { missed: r.missed(), report: r.report.clone() }
        })
    } else if brrdf {
        let opts = brrdf::BrrdfDemoOptions {
            quick: args.quick,
            out: args.out.join("brrdf"),
            seed: args.seed,
            progress,
            real_time: args.real_time,
        };
        brrdf::run_brrdf(&opts).map(|r| {
            eprintln!("report: {}", r.report.display());
            DemoRun { missed: r.missed(), report: r.report.clone() }
        })
    } else if display {
        let opts = display::DisplayDemoOptions {
            quick: args.quick,
            out: args.out.join("display"),
            seed: args.seed,
            progress,
            real_time: args.real_time,
        };
        display::run_display(&opts).map(|r| {
            eprintln!("report: {}", r.report.display());
            DemoRun { missed: r.missed(), report: r.report.clone() }
        })
    } else if firs {
        let opts = firs::FirsDemoOptions {
            objects: vec![firs::FirsDemoObject::Sphere, firs::FirsDemoObject::Faceted],
            volume: true,
            quick: args.quick,
            out: args.out.join("firs"),
            seed: args.seed,
            progress,
            real_time: args.real_time,
        };
        firs::run_firs(&opts).map(|r| DemoRun { missed: r.missed(), report: r.report.clone() })
    } else if lls {
        let opts = lls::DemoOptions {
            quick: args.quick,
            out: args.out.join("lls"),
            seed: args.seed,
            progress,
            real_time: args.real_time,
            step_mm: args.step_mm,
            camera_gamma: args.camera_gamma,
        };
        lls::run_lls(&opts).map(|(acc, report)| DemoRun {
            missed: acc.targets().into_iter().filter(|t| !t.3).map(|t| t.0.to_string()).collect(),
            report,
        })
    } else {
        Err(err(
            USAGE,
            format!(
                "`lightrig demo {}`: the methods with a demo are: lls, firs, display, brrdf, disco",
                args.method
            ),
        ))
    }
}

/// A demo's rig: its rig file written as `rig.toml` in the demo's directory (a valid rig file a
/// user can read and run), parsed and planned for the virtual controller.
pub struct DemoRig {
    /// The rig file's text.
    pub text: String,
    /// The rig file.
    pub rig: RigFile,
    /// Its plan.
    pub plan: Plan,
    /// The virtual controller it runs on.
    pub info: DeviceInfo,
}

impl DemoRig {
    /// Writes `text` to `out/rig.toml`, parses and plans it.
    pub fn write(out: &Path, text: String) -> Result<Self, CliError> {
        let rig_path = out.join("rig.toml");
        std::fs::write(&rig_path, &text).map_err(io(&rig_path))?;
        let rig = RigFile::parse(&text, &rig_path).map_err(|e| err(INPUT, e.to_string()))?;
        let info = virtual_device_info();
        from_rig::check_keys(&rig).map_err(|e| err(INPUT, e.to_string()))?;
        let plan = from_rig::plan(&rig, &info).map_err(|e| err(INPUT, e.to_string()))?;
        Ok(Self { text, rig, plan, info })
    }

    /// Acquires the plan on the virtual rig exactly as `lightrig acquire` does, into a fresh
    /// `out/session`, the virtual camera 0 rendering `scene` through `sensor` into a fresh
    /// `out/camera` and following the board over each exposure; `out/fit` is cleared for the
    /// fit. `progress` follows the frames. Returns the camera (and with it the scene).
    pub fn acquire<S: Scene>(
        &self,
        out: &Path,
        scene: S,
        sensor: Sensor,
        real_time: bool,
        progress: &ProgressBar,
    ) -> Result<VirtualCamera<S>, CliError> {
        for d in ["session", "camera", "fit"] {
            let d = out.join(d);
            if d.exists() {
                std::fs::remove_dir_all(&d).map_err(io(&d))?;
            }
        }
        let (session_dir, camera_dir) = (out.join("session"), out.join("camera"));
        let (virtual_rig, timeline) = connect_for_camera(&self.rig, self.info, real_time);
        let transport: Box<dyn Transport> = Box::new(virtual_rig);
        let mut client = bring_up_on(&self.rig, transport)?;
        let manifest = Manifest::new(self.text.clone(), client.info(), plan_summary(&self.plan));
        let mut session = Session::create(&session_dir, manifest).map_err(failure)?;
        let context = CONTEXT.with(|c| c.borrow().clone());
        // Stop from the page, or the caller's interrupt, stops this virtual device as Ctrl-C
        // stops a real one.
        let interrupt = context.interrupt.clone().unwrap_or_default();
        if context.interrupt.is_some() || context.serve.is_some() {
            client.set_interrupt(interrupt.clone());
        }
        let served = match context.serve.as_deref() {
            Some(addr) => {
                let device = client.transport().describe();
                let s = crate::cmd::live::serve(addr, "demo", &session_dir, &device, interrupt)?;
                s.live.set_method(&self.plan.method);
                s.attach(&mut session, &mut client);
                Some(s)
            }
            None => None,
        };
        lightrig_host::response::attach(&self.rig, &session_dir)
            .map_err(|e| crate::error::err(crate::error::INPUT, e))?;
        let mut camera = VirtualCamera::new(&self.rig, 0, scene, sensor, self.info.tick_hz, &camera_dir)
            .map_err(io(&camera_dir))?;
        camera.follow(timeline);
        let bar = progress.clone();
        camera.on_frame(move |n| bar.set_position(n));
        let result =
            acquire::run(&mut client, &mut session, &self.plan, &mut camera, |_| {}).map_err(|e| match e {
                acquire::AcquireError::Device(lightrig_host::client::ClientError::Interrupted { .. }) => {
                    err(crate::error::INTERRUPTED, e.to_string())
                }
                other => failure(other),
            });
        if let Some(s) = &served {
            s.ended(&result);
        }
        result.map(|()| camera)
    }
}

/// Writes a scene's description as `dir/scene.json` (creating `dir`).
pub fn write_scene_json(dir: &Path, scene: &impl serde::Serialize) -> Result<PathBuf, CliError> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let json = serde_json::to_string_pretty(scene).map_err(failure)?;
    let p = dir.join("scene.json");
    std::fs::write(&p, json + "\n").map_err(io(&p))?;
    Ok(p)
}

/// A progress bar, hidden unless `show`.
pub fn bar(show: bool, len: u64, what: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let b = ProgressBar::new(len);
    b.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    b.set_message(what.to_string());
    b
}

/// An accuracy target against the ground truth: `(name, value, limit, met)`.
pub type Target = (&'static str, f64, f64, bool);

/// A demo's `report.md`, in Markdown.
#[derive(Debug, Default)]
pub struct Report(pub String);

impl Report {
    /// A line (a paragraph ends with an empty one).
    pub fn line(&mut self, text: impl std::fmt::Display) {
        let _ = writeln!(self.0, "{text}");
    }

    /// The targets as a table: `columns` heads the name, value and limit columns, then "met";
    /// `bound` goes before each limit (`"≤ "`, or nothing where the name says which way).
    pub fn targets(&mut self, columns: [&str; 3], bound: &str, targets: &[Target]) {
        let [name, value, limit] = columns;
        let _ = writeln!(self.0, "| {name} | {value} | {limit} | met |\n|---|---|---|---|");
        for (name, v, limit, met) in targets {
            let met = if *met { "yes" } else { "**no**" };
            let _ = writeln!(self.0, "| {name} | {v:.4} | {bound}{limit} | {met} |");
        }
    }

    /// Writes the report to `path` (`report.md`) and beside it as an HTML page
    /// (`report.html`: the same text, its tables and pictures, for a browser).
    pub fn write(&self, path: &std::path::Path) -> Result<(), crate::error::CliError> {
        std::fs::write(path, &self.0).map_err(crate::error::io(path))?;
        let html_path = path.with_extension("html");
        std::fs::write(&html_path, self.html()).map_err(crate::error::io(&html_path))
    }

    /// The report as a standalone HTML page (CommonMark with tables, by pulldown-cmark).
    pub fn html(&self) -> String {
        use pulldown_cmark::{html, Options, Parser};
        let title = self.0.lines().find_map(|l| l.strip_prefix("# ")).unwrap_or("lightrig report");
        let mut body = String::new();
        html::push_html(&mut body, Parser::new_ext(&self.0, Options::ENABLE_TABLES));
        let escaped = title.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;");
        format!(
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{escaped}</title>\n\
             <style>body {{ font-family: sans-serif; max-width: 60em; margin: 2em auto; }} \
             table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #ccc; padding: 0.2em 0.5em; }} \
             img {{ image-rendering: pixelated; max-width: 100%; }}</style>\n</head>\n<body>\n{body}</body>\n</html>\n"
        )
    }

    /// The files a fit wrote, one bullet each, after a heading line.
    pub fn outputs(&mut self, files: &[PathBuf]) {
        let _ = writeln!(self.0, "\nOutputs:\n");
        for f in files {
            let _ = writeln!(self.0, "- `{}`", f.display());
        }
    }
}
