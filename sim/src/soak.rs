//! `lightrig soak`: a long acquisition through the whole virtual rig (the firmware controller,
//! the host's client, acquisition engine and sessions) over a wire that drops, flips and
//! duplicates bytes. It shows what a lab's overnight run needs: every trigger's frame stored
//! once and paired with that trigger, none lost, none twice, the link riding out the damage.
//!
//! The run is split into sessions of a few steps each (a real overnight run would be one, but
//! a million frame files in one directory is a file-system test, not a link test). Each is
//! read back, verified (every file's size and CRC-32) and checked frame by frame against the
//! trigger that made it, then removed.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use lightrig_firmware::sim::{virtual_device_info, SimBoard};
use lightrig_host::acquire::{self, plan_summary, Captured, FrameInput};
use lightrig_host::client::Client;
use lightrig_host::plan::{Plan, Step};
use lightrig_host::session::{journal_records, Manifest, Record, Session};
use lightrig_host::transport::Transport;
use lightrig_protocol::config::{CameraConfig, ConfigItem, Input, Polarity};
use lightrig_protocol::event::TriggerEvent;
use lightrig_protocol::link::LinkStats;
use lightrig_protocol::{Command, Event};

use crate::transport::{Damage, Impairment, VirtualTransport};

/// How the soak runs.
#[derive(Debug, Clone)]
pub struct Options {
    /// Camera triggers in all.
    pub triggers: u64,
    /// Triggers per step (one device sequence each).
    pub per_step: u32,
    /// Steps per session.
    pub steps_per_session: u32,
    /// Bytes dropped, flipped and duplicated on the wire, each per million, each direction.
    pub damage_ppm: u32,
    /// Seed of the damage pattern.
    pub seed: u64,
    /// Where the sessions are written (each removed once checked).
    pub dir: PathBuf,
}

/// What the soak saw.
#[derive(Debug, Clone, Default)]
pub struct Report {
    /// Triggers the plan fired.
    pub triggers: u64,
    /// Frames stored, each paired with its own trigger.
    pub frames: u64,
    /// Triggers without a frame.
    pub missing: u64,
    /// Frames without a trigger, or a trigger's second frame.
    pub extra: u64,
    /// Frames stored under a trigger other than their own.
    pub mispaired: u64,
    /// Trigger events journaled (each once: the journal refuses a repeat).
    pub trigger_events: u64,
    /// Steps, and attempts at them (an attempt is repeated when the link is lost mid-step).
    pub steps: u64,
    /// Attempts at the steps.
    pub attempts: u64,
    /// Sessions written and checked.
    pub sessions: u64,
    /// What the wire did.
    pub damage: Damage,
    /// The host end's link counters.
    pub host_link: LinkStats,
    /// Simulated device time, µs.
    pub simulated_us: u64,
    /// Wall-clock time.
    pub wall: Duration,
}

impl Report {
    /// Whether every trigger's frame was stored once and paired with it.
    pub fn clean(&self) -> bool {
        self.frames == self.triggers
            && self.missing == 0
            && self.extra == 0
            && self.mispaired == 0
            && self.trigger_events == self.triggers
    }
}

/// Trigger spacing, ticks (µs on the virtual device): 500 frames/s.
const PERIOD: u32 = 2_000;
const EXPOSURE: u32 = 500;

/// A camera that makes, for every trigger, a small frame naming that trigger.
struct NamingCamera {
    ready: Vec<Captured>,
}

/// What [`NamingCamera`] writes for a trigger.
fn frame_text(sequence: u32, frame: u32, tick: u64) -> String {
    format!("sequence {sequence} frame {frame} tick {tick}\n")
}

impl FrameInput for NamingCamera {
    fn begin_step(&mut self, _step: &Step) -> std::io::Result<()> {
        self.ready.clear();
        Ok(())
    }

    fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
        self.ready.push(Captured {
            camera: t.camera,
            frame: Some(t.frame),
            ext: "txt".into(),
            data: frame_text(t.sequence, t.frame, t.tick).into_bytes(),
            host_us: host_us.unwrap_or(0.0) + f64::from(EXPOSURE),
            before_step: false,
            stamp: None,
        });
        Ok(())
    }

    fn poll(&mut self, _now_us: f64) -> std::io::Result<Vec<Captured>> {
        Ok(std::mem::take(&mut self.ready))
    }
}

fn plan(first_step: u32, steps: u32, per_step: u32) -> Plan {
    let steps = (first_step..first_step + steps)
        .map(|id| {
            Step::new(id, format!("burst {id}"), serde_json::Value::Null, move |b| {
                for _ in 0..per_step {
                    b.wait(PERIOD).shoot(0, EXPOSURE, "");
                }
            })
        })
        .collect();
    // No step acquired again: the soak counts every frame lost.
    let meta = serde_json::Value::Null;
    Plan { method: "soak".into(), tick_hz: 1_000_000, steps, frame_bytes: 48, meta, lost_retries: 0 }
}

/// Runs the soak; `progress` hears the triggers done so far after each session.
pub fn run(opts: &Options, progress: impl FnMut(&Report)) -> Result<Report> {
    run_with(opts, &mut NamingCamera { ready: Vec::new() }, progress)
}

fn run_with(
    opts: &Options,
    frames: &mut dyn FrameInput,
    mut progress: impl FnMut(&Report),
) -> Result<Report> {
    ensure!(opts.per_step > 0 && opts.steps_per_session > 0, "steps need triggers and sessions steps");
    let started = Instant::now();
    let mut transport = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let d = opts.damage_ppm;
    transport.impair(Impairment { drop_ppm: d, corrupt_ppm: d, duplicate_ppm: d, seed: opts.seed });
    let mut client =
        Client::connect(transport, opts.seed as u32 | 1).context("connecting to the virtual rig")?;
    let camera = CameraConfig {
        camera: 0,
        pulse_ticks: 100,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 1_000,
    };
    client.request(Command::Configure(ConfigItem::Camera(camera))).context("configuring the camera")?;
    let mut report = Report::default();
    let per_session = u64::from(opts.per_step) * u64::from(opts.steps_per_session);
    let mut next_step = 0u32;
    while report.triggers < opts.triggers {
        let left = opts.triggers - report.triggers;
        let steps = left.min(per_session).div_ceil(u64::from(opts.per_step)) as u32;
        let plan = plan(next_step, steps, opts.per_step);
        next_step += steps;
        let dir = opts.dir.join(format!("soak-{}-{:06}", std::process::id(), report.sessions));
        let _ = std::fs::remove_dir_all(&dir);
        let manifest = Manifest::new("# lightrig soak", client.info(), plan_summary(&plan));
        let mut session = Session::create(&dir, manifest).with_context(|| dir.display().to_string())?;
        acquire::run(&mut client, &mut session, &plan, frames, |_| {})
            .with_context(|| format!("session {}", dir.display()))?;
        drop(session);
        check_session(&dir, &plan, &mut report)?;
        std::fs::remove_dir_all(&dir).with_context(|| dir.display().to_string())?;
        report.sessions += 1;
        report.damage = client.transport().damage();
        report.host_link = *client.link_stats();
        report.simulated_us = client.transport().now_us();
        report.wall = started.elapsed();
        progress(&report);
    }
    Ok(report)
}

/// Reads a finished session back and counts what it holds against the plan.
fn check_session(dir: &Path, plan: &Plan, report: &mut Report) -> Result<()> {
    let (s, _) = Session::read(dir).with_context(|| dir.display().to_string())?;
    ensure!(s.is_done(), "{}: not complete", dir.display());
    let problems = s.verify();
    ensure!(problems.is_empty(), "{}: {problems:?}", dir.display());
    for step in &plan.steps {
        report.triggers += step.shot_count() as u64;
        report.steps += 1;
        report.attempts += s.state().steps.get(&step.id).map_or(0, |a| a.len() as u64);
        let (_, attempt) = s.state().done_attempt(step.id).context("a done step")?;
        report.missing += attempt.missing.len() as u64;
        report.extra += attempt.extra.len() as u64;
        for f in attempt.frames.values() {
            let text = std::fs::read_to_string(dir.join(&f.file))?;
            if text == frame_text(f.sequence, f.frame, f.tick) {
                report.frames += 1;
            } else {
                report.mispaired += 1;
            }
        }
    }
    // Trigger events of the attempts that count, as journaled: each exactly once.
    let done: std::collections::HashSet<u32> = plan
        .steps
        .iter()
        .filter_map(|st| s.state().done_attempt(st.id).map(|(_, a)| a.sequence_id))
        .collect();
    for r in journal_records(dir)? {
        if let Record::Event { event: Event::Trigger(t), .. } = r {
            report.trigger_events += u64::from(done.contains(&t.sequence));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(name: &str, damage_ppm: u32) -> Options {
        let dir = std::env::temp_dir().join(format!("lightrig-soak-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Options { triggers: 2_000, per_step: 200, steps_per_session: 4, damage_ppm, seed: 7, dir }
    }

    #[test]
    fn a_short_soak_over_a_badly_damaged_wire_pairs_every_frame_once() {
        let opts = options("clean", 1_000);
        let mut seen = Vec::new();
        let r = run(&opts, |r| seen.push(r.triggers)).unwrap();
        assert_eq!(seen, [800, 1600, 2000], "a session of 4 steps at a time, the last one short");
        assert!(r.clean(), "{r:?}");
        assert_eq!(
            (r.triggers, r.frames, r.trigger_events, r.steps, r.sessions),
            (2_000, 2_000, 2_000, 10, 3)
        );
        assert!(r.damage.dropped > 0 && r.damage.flipped > 0 && r.damage.duplicated > 0, "{:?}", r.damage);
        assert!(r.host_link.retransmits > 0 && r.host_link.rejected() > 0, "the link had work to do");
        assert_eq!(std::fs::read_dir(&opts.dir).unwrap().count(), 0, "every session removed once checked");
        std::fs::remove_dir_all(&opts.dir).unwrap();
    }

    /// [`NamingCamera`] whose frames 3 and 4 of every step come numbered the other way round.
    struct Swapping(NamingCamera);

    impl FrameInput for Swapping {
        fn begin_step(&mut self, step: &Step) -> std::io::Result<()> {
            self.0.begin_step(step)
        }
        fn on_trigger(&mut self, t: &TriggerEvent, host_us: Option<f64>) -> std::io::Result<()> {
            self.0.on_trigger(t, host_us)?;
            let last = self.0.ready.last_mut().expect("a frame");
            if let Some(f @ (3 | 4)) = last.frame {
                last.frame = Some(7 - f);
            }
            Ok(())
        }
        fn poll(&mut self, now_us: f64) -> std::io::Result<Vec<Captured>> {
            self.0.poll(now_us)
        }
    }

    #[test]
    fn frames_paired_with_the_wrong_trigger_are_counted_and_fail_the_soak() {
        let opts = Options { triggers: 400, ..options("swapped", 0) };
        let r = run_with(&opts, &mut Swapping(NamingCamera { ready: Vec::new() }), |_| {}).unwrap();
        assert_eq!((r.frames, r.mispaired), (396, 4), "two swapped frames in each of two steps");
        assert!(!r.clean());
        std::fs::remove_dir_all(&opts.dir).unwrap();
    }
}
