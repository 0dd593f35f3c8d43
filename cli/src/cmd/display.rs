//! `lightrig display RIG --alpha AX[,AY]`: shows a Ward roughness on a BRDF display and keeps
//! showing it, taking new ones from standard input (`0.05,0.1` and Enter) and changing the
//! coils live over the controller's amplitude ramps (no click); at end of input it fades the
//! coils and leaves. An α the calibrated display cannot reach is refused with its range.

use std::io::BufRead;
use std::path::PathBuf;

use lightrig_host::bringup::{bring_up_with, BringUpHooks};
use lightrig_host::client::{Client, Interrupt};
use lightrig_host::plan::display::{coil_actions, partials_for};
use lightrig_host::plan::from_rig::{display_calibration, display_calibration_at, display_max_slope};
use lightrig_host::rigfile::RigFile;
use lightrig_host::transport::{Connect, Transport};
use lightrig_pipelines::display::Calibration;
use lightrig_protocol::sequence::Partial;
use lightrig_protocol::Command;

use super::acquire::{connect_spec, on_ctrl_c, open};
use crate::error::{err, CliError, DEVICE, INPUT, USAGE};

/// Arguments of `lightrig display`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The display's rig file (its `[plan] calibration` names the calibration).
    pub rig: PathBuf,
    /// Ward roughness to show: `AX,AY`, or one value for both axes.
    #[arg(long)]
    pub alpha: String,
    /// The display calibration (`lightrig fit display`'s), instead of the rig file's.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Override the rig file's `[device] connect`.
    #[arg(long)]
    pub connect: Option<Connect>,
    /// How long each change takes, ms (the controller ramps every partial's amplitude).
    #[arg(long, default_value_t = 200.0)]
    pub ramp_ms: f64,
}

/// `AX,AY` or `A`.
pub fn parse_alpha(s: &str) -> Result<[f64; 2], String> {
    let bad = || format!("α `{s}`: give AX,AY (e.g. 0.08,0.04) or one value for both axes");
    let v: Vec<f64> =
        s.split(',').map(|x| x.trim().parse::<f64>().map_err(|_| bad())).collect::<Result<_, _>>()?;
    match v[..] {
        [a] => Ok([a, a]),
        [x, y] => Ok([x, y]),
        _ => Err(bad()),
    }
}

struct Hooks(Option<std::sync::Arc<Interrupt>>);

impl BringUpHooks for Hooks {
    fn say(&mut self, what: &str) {
        eprintln!("{what}");
    }
    fn interrupt(&self) -> Option<std::sync::Arc<Interrupt>> {
        self.0.clone()
    }
}

/// Sends `alpha`'s partials to both coils, ramping over `ramp` ticks; refuses an unreachable α.
fn set(
    client: &mut Client<Box<dyn Transport>>,
    cal: &Calibration,
    alpha: [f64; 2],
    max_slope: f64,
    ramp: u32,
) -> Result<(), CliError> {
    let channels = partials_for(cal, alpha, max_slope).map_err(|e| err(USAGE, e.to_string()))?;
    send(client, &channels, ramp)
}

fn send(
    client: &mut Client<Box<dyn Transport>>,
    channels: &[(u8, Vec<Partial>)],
    ramp: u32,
) -> Result<(), CliError> {
    for action in coil_actions(channels, ramp).map_err(|e| err(USAGE, e.0))? {
        client.request(Command::Immediate(action)).map_err(|e| err(DEVICE, e.to_string()))?;
    }
    Ok(())
}

/// Runs `lightrig display`.
pub fn run(args: &Args) -> Result<(), CliError> {
    let text =
        std::fs::read_to_string(&args.rig).map_err(|e| err(INPUT, format!("{}: {e}", args.rig.display())))?;
    let rig = RigFile::parse(&text, &args.rig).map_err(|e| err(INPUT, e.to_string()))?;
    let cal = match &args.calibration {
        Some(c) => display_calibration_at(&rig, c),
        None => display_calibration(&rig),
    }
    .map_err(|e| err(INPUT, e.to_string()))?;
    let max_slope = display_max_slope(&rig).map_err(|e| err(INPUT, e.to_string()))?;
    let alpha = parse_alpha(&args.alpha).map_err(|e| err(USAGE, e))?;
    // Refuse before touching the device.
    partials_for(&cal, alpha, max_slope).map_err(|e| err(USAGE, e.to_string()))?;
    let spec = connect_spec(&rig, args.connect.as_ref());
    let (transport, _) = open(&rig, &spec)?;
    let mut client =
        bring_up_with(&rig, transport, &mut Hooks(on_ctrl_c())).map_err(|e| err(DEVICE, e.to_string()))?;
    let hz = f64::from(client.info().tick_hz);
    let ramp = (args.ramp_ms.max(0.0) * 1e-3 * hz).round() as u32;
    set(&mut client, &cal, alpha, max_slope, ramp)?;
    eprintln!(
        "showing αx = {}, αy = {}; type another (AX,AY) and Enter to change it, end of input to fade and stop",
        alpha[0], alpha[1]
    );
    let stdin = std::io::stdin();
    loop {
        let mut line = String::new();
        // The link (and the controller's heartbeat) is kept alive while waiting for input.
        let read = client.busy(|| stdin.lock().read_line(&mut line));
        match read {
            Ok(0) | Err(_) => break,
            Ok(_) if line.trim().is_empty() => continue,
            Ok(_) => {}
        }
        match parse_alpha(line.trim())
            .and_then(|a| set(&mut client, &cal, a, max_slope, ramp).map(|()| a).map_err(|e| e.message))
        {
            Ok(a) => eprintln!("showing αx = {}, αy = {}", a[0], a[1]),
            Err(e) => eprintln!("refused: {e}"),
        }
    }
    let silence: Vec<(u8, Vec<Partial>)> = cal.axes.iter().map(|a| (a.channel, Vec::new())).collect();
    send(&mut client, &silence, ramp)?;
    // Let the fade play out before the host leaves.
    client.idle(u64::from(ramp) + 50_000).map_err(|e| err(DEVICE, e.to_string()))?;
    eprintln!("faded to silence");
    Ok(())
}
