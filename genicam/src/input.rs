//! The Aravis side: a camera opened, configured and streamed on a thread of its own.

use std::io;
use std::sync::mpsc::{channel, Receiver, Sender, TryRecvError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use aravis::prelude::*;
use aravis::{Buffer, BufferStatus, Camera, GvStreamOption, GvStreamSocketBuffer, PixelFormat, Stream};
use glib::prelude::*;
use lightrig_host::acquire::{Captured, FrameInput};
use lightrig_host::plan::Step;
use lightrig_host::rigfile::GenicamSource;
use lightrig_host::session::CameraStamp;
use lightrig_protocol::event::TriggerEvent;

use crate::ids::{advance, frames_after};
use crate::CameraInfo;

/// Aravis's global state: initialised once per process.
fn init() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let _ = aravis::Aravis::initialize();
    });
}

/// The cameras discovery finds, then those at `addresses` not already found; an address that
/// does not answer is an error naming it.
pub fn cameras(addresses: &[String]) -> Result<Vec<CameraInfo>, String> {
    init();
    let s = |c: &std::ffi::CStr| c.to_string_lossy().into_owned();
    // SAFETY: Aravis's device list is global state; this process lists it from one thread.
    let mut out: Vec<CameraInfo> = unsafe { aravis::get_device_list() }
        .iter()
        .map(|d| CameraInfo {
            id: s(&d.id),
            vendor: s(&d.vendor),
            model: s(&d.model),
            protocol: s(&d.protocol),
            address: s(&d.address),
        })
        .collect();
    for a in addresses {
        if out.iter().any(|c| &c.address == a || &c.id == a) {
            continue;
        }
        let cam = Camera::new(Some(a)).map_err(|e| {
            format!("{a}: no GenICam camera answers there ({e}); check the address and that the camera is on this subnet")
        })?;
        let g = |r: Result<glib::GString, glib::Error>| r.map(|v| v.to_string()).unwrap_or_default();
        out.push(CameraInfo {
            id: format!(
                "{}-{}-{}",
                g(cam.vendor_name()),
                g(cam.model_name()),
                g(cam.string("DeviceSerialNumber"))
            ),
            vendor: g(cam.vendor_name()),
            model: g(cam.model_name()),
            protocol: if cam.is_gv_device() { "GigEVision".into() } else { "USB3Vision".into() },
            address: a.clone(),
        });
    }
    Ok(out)
}

/// What the stream thread hands over.
enum Out {
    Frame { id: u64, time_ns: u64, status: Option<String>, png: Result<Vec<u8>, String> },
    Error(String),
}

/// A GenICam camera as a frame input.
pub struct GenicamInput {
    camera: u8,
    address: String,
    software: bool,
    fire: Option<Sender<()>>,
    frames: Receiver<Out>,
    worker: Option<JoinHandle<()>>,
    /// The id the next software trigger will produce.
    next_id: Option<u64>,
    /// The id of the current step's frame 0.
    base: Option<u64>,
    /// The last id seen.
    last: Option<u64>,
    lost: Vec<(u8, u32, String)>,
}

fn err(address: &str, what: &str, e: impl std::fmt::Display) -> String {
    format!("GenICam camera {address}: {what}: {e}")
}

impl GenicamInput {
    /// Opens and configures the camera, starts its stream.
    pub fn open(camera: u8, src: &GenicamSource, min_interval_us: f64) -> Result<Self, String> {
        init();
        let a = src.address.as_str();
        let cam = Camera::new(Some(a)).map_err(|e| {
            err(
                a,
                "cannot open it",
                format!("{e}; `lightrig devices --genicam ADDRESS` lists what this host sees (a camera on another subnet or on loopback is opened by its address)"),
            )
        })?;
        let software = src.trigger.eq_ignore_ascii_case("software");
        cam.set_trigger(if software { "Software" } else { &src.trigger })
            .map_err(|e| err(a, &format!("trigger = \"{}\"", src.trigger), e))?;
        if let Some(act) = &src.activation {
            cam.set_string("TriggerActivation", act)
                .map_err(|e| err(a, &format!("activation = \"{act}\""), e))?;
        }
        if let Some(f) = &src.pixel_format {
            cam.set_pixel_format_from_string(f).map_err(|e| err(a, &format!("pixel_format = \"{f}\""), e))?;
        }
        if let Some(x) = src.exposure_us {
            cam.set_exposure_time(x).map_err(|e| err(a, &format!("exposure_us = {x}"), e))?;
        }
        if cam.is_gv_device() {
            // The packet socket needs privileges; the plain socket, sized for the payload,
            // streams reliably here.
            cam.gv_set_stream_options(GvStreamOption::PACKET_SOCKET_DISABLED);
        }
        let payload = cam.payload().map_err(|e| err(a, "payload size", e))? as usize;
        let stream = cam.create_stream().map_err(|e| err(a, "creating the stream", e))?;
        if cam.is_gv_device() {
            stream.set_property("socket-buffer", GvStreamSocketBuffer::Auto);
        }
        for _ in 0..src.buffers {
            stream.push_buffer(Buffer::new_allocate(payload));
        }
        cam.start_acquisition().map_err(|e| err(a, "starting acquisition", e))?;
        let mut me = GenicamInput {
            camera,
            address: a.to_string(),
            software,
            fire: None,
            frames: channel().1,
            worker: None,
            next_id: None,
            base: None,
            last: None,
            lost: Vec::new(),
        };
        if software {
            // One frame to learn the camera's counter: then every software trigger's frame id
            // is known before it arrives. (The first frame after the stream starts may come
            // back incomplete; its id counts all the same.)
            let mut id = None;
            for _ in 0..3 {
                cam.software_trigger().map_err(|e| err(a, "software trigger", e))?;
                if let Some(b) = stream.timeout_pop_buffer(2_000_000) {
                    id = Some(b.frame_id());
                    stream.push_buffer(b);
                    break;
                }
            }
            let id =
                id.ok_or_else(|| err(a, "no frame within 2 s of a software trigger", "is it streaming?"))?;
            me.last = Some(id);
            me.next_id = Some(advance(id, 1));
        }
        // A little under the controller's own spacing, so that a late trigger event does not
        // delay every software trigger after it.
        let gap = Duration::from_micros((0.8 * min_interval_us).max(0.0) as u64);
        let (fire, fired) = channel::<()>();
        let (tx, frames) = channel::<Out>();
        let address = a.to_string();
        me.worker = Some(std::thread::spawn(move || stream_loop(cam, stream, fired, tx, gap, address)));
        me.fire = Some(fire);
        me.frames = frames;
        Ok(me)
    }

    fn take(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        let mut out = Vec::new();
        loop {
            match self.frames.try_recv() {
                Ok(Out::Frame { id, time_ns, status, png }) => {
                    let stamp = Some(CameraStamp { id, time_ns });
                    self.last = Some(id);
                    let base = *self.base.get_or_insert(id);
                    let Some(k) = frames_after(base, id) else {
                        // A frame of an earlier step, late: kept as an extra.
                        if let Ok(data) = png {
                            out.push(self.captured(Some(id as u32), data, now_us, true, stamp));
                        }
                        continue;
                    };
                    let k = k as u32;
                    match (status, png) {
                        (None, Ok(data)) => out.push(self.captured(Some(k), data, now_us, false, stamp)),
                        (Some(s), _) => self.lost.push((
                            self.camera,
                            k,
                            format!("the camera delivered frame id {id} incomplete ({s}): lost on the way"),
                        )),
                        (None, Err(e)) => self.lost.push((self.camera, k, format!("frame id {id}: {e}"))),
                    }
                }
                Ok(Out::Error(e)) => return Err(io::Error::other(e)),
                Err(TryRecvError::Empty) => return Ok(out),
                Err(TryRecvError::Disconnected) => {
                    return Err(io::Error::other(format!(
                        "GenICam camera {}: its stream thread stopped",
                        self.address
                    )))
                }
            }
        }
    }

    fn captured(
        &self,
        frame: Option<u32>,
        data: Vec<u8>,
        host_us: f64,
        before_step: bool,
        stamp: Option<CameraStamp>,
    ) -> Captured {
        Captured { camera: self.camera, frame, ext: "png".into(), data, host_us, before_step, stamp }
    }
}

/// How long a software trigger's frame may take before the next trigger is fired all the same
/// (its leader packet was lost: the frame never comes, the camera's counter moved on).
const FRAME_DUE: Duration = Duration::from_secs(1);

/// Whether the next software trigger may be fired now: one is pending, the last was fired at
/// least `gap` ago, and its frame has come back (or is overdue). A camera ignores a trigger
/// that comes while it is still busy with the last one (Aravis's fake camera reads its trigger
/// register once per 40 ms frame period, so two triggers in one period make one frame): its
/// counter would not move, and every later frame would pair with the trigger before its own.
pub(crate) fn may_fire(
    pending: u64,
    since_fire: Option<Duration>,
    unanswered: Option<Duration>,
    gap: Duration,
) -> bool {
    pending > 0 && since_fire.is_none_or(|t| t >= gap) && unanswered.is_none_or(|t| t >= FRAME_DUE)
}

/// Fires the software triggers asked for, one at a time ([`may_fire`]), and hands over every
/// buffer.
fn stream_loop(
    cam: Camera,
    stream: Stream,
    fired: Receiver<()>,
    tx: Sender<Out>,
    gap: Duration,
    address: String,
) {
    let mut pending = 0u64;
    let mut last_fire: Option<Instant> = None;
    // When the trigger whose frame has not come back yet was fired.
    let mut unanswered: Option<Instant> = None;
    loop {
        loop {
            match fired.try_recv() {
                Ok(()) => pending += 1,
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    let _ = cam.stop_acquisition();
                    return;
                }
            }
        }
        if may_fire(pending, last_fire.map(|t| t.elapsed()), unanswered.map(|t| t.elapsed()), gap) {
            if let Err(e) = cam.software_trigger() {
                let _ = tx.send(Out::Error(err(&address, "software trigger", e)));
                return;
            }
            pending -= 1;
            last_fire = Some(Instant::now());
            unanswered = last_fire;
        }
        if let Some(b) = stream.timeout_pop_buffer(2_000) {
            unanswered = None;
            let (id, time_ns) = (b.frame_id(), b.timestamp());
            let out = match b.status() {
                BufferStatus::Success => {
                    let name = format_name(b.image_pixel_format());
                    let png = crate::encode::png(
                        b.image_width().max(0) as u32,
                        b.image_height().max(0) as u32,
                        name,
                        &b.image_data(),
                    );
                    Out::Frame { id, time_ns, status: None, png }
                }
                other => {
                    Out::Frame { id, time_ns, status: Some(format!("{other:?}")), png: Err(String::new()) }
                }
            };
            stream.push_buffer(b);
            if tx.send(out).is_err() {
                let _ = cam.stop_acquisition();
                return;
            }
        }
    }
}

/// The GenICam name of the formats [`crate::encode::png`] stores.
fn format_name(f: PixelFormat) -> &'static str {
    const NAMES: [(PixelFormat, &str); 10] = [
        (PixelFormat::MONO_8, "Mono8"),
        (PixelFormat::MONO_10, "Mono10"),
        (PixelFormat::MONO_12, "Mono12"),
        (PixelFormat::MONO_14, "Mono14"),
        (PixelFormat::MONO_16, "Mono16"),
        (PixelFormat::RGB_8_PACKED, "RGB8"),
        (PixelFormat::BAYER_RG_8, "BayerRG8"),
        (PixelFormat::BAYER_GR_8, "BayerGR8"),
        (PixelFormat::BAYER_GB_8, "BayerGB8"),
        (PixelFormat::BAYER_BG_8, "BayerBG8"),
    ];
    NAMES.iter().find(|(p, _)| *p == f).map_or("another (packed or unknown)", |(_, n)| n)
}

impl FrameInput for GenicamInput {
    fn begin_step(&mut self, _step: &Step) -> io::Result<()> {
        // Frames before the step were drained by the engine's poll; the step's frame 0 is the
        // next software trigger's, or (a line trigger) the first frame after the last seen.
        self.lost.clear();
        self.base = match (self.software, self.next_id, self.last) {
            (true, Some(next), _) => Some(next),
            (false, _, Some(last)) => Some(advance(last, 1)),
            _ => None,
        };
        Ok(())
    }

    fn on_trigger(&mut self, t: &TriggerEvent, _host_us: Option<f64>) -> io::Result<()> {
        if !self.software || t.camera != self.camera {
            return Ok(());
        }
        self.next_id = self.next_id.map(|n| advance(n, 1));
        let fire = self.fire.as_ref().ok_or_else(|| io::Error::other("the camera is closed"))?;
        fire.send(()).map_err(|_| {
            io::Error::other(format!("GenICam camera {}: its stream thread stopped", self.address))
        })
    }

    fn poll(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        self.take(now_us)
    }

    fn poll_now(&mut self, now_us: f64) -> io::Result<Vec<Captured>> {
        // The frames are already in a channel: taking them never waits.
        self.take(now_us)
    }

    fn lost(&mut self) -> Vec<(u8, u32, String)> {
        std::mem::take(&mut self.lost)
    }

    fn stamps_follow_triggers(&self) -> bool {
        // A line-triggered camera stamps each frame at its trigger; software triggers carry
        // the host's latency (and the fake camera stamps on its own 40 ms frame clock).
        !self.software
    }
}

impl Drop for GenicamInput {
    fn drop(&mut self) {
        drop(self.fire.take());
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_software_trigger_waits_for_the_last_ones_frame_or_its_deadline() {
        let ms = Duration::from_millis;
        let gap = ms(40);
        // Nothing asked, or asked within the gap: not yet.
        assert!(!may_fire(0, None, None, gap));
        assert!(!may_fire(1, Some(ms(39)), None, gap));
        // The first trigger, and one a gap after a trigger whose frame is back.
        assert!(may_fire(1, None, None, gap));
        assert!(may_fire(3, Some(ms(40)), None, gap));
        // The last frame not back: wait for it, however long ago it was fired, up to FRAME_DUE.
        assert!(!may_fire(3, Some(ms(500)), Some(ms(500)), gap));
        assert!(!may_fire(3, Some(FRAME_DUE - ms(1)), Some(FRAME_DUE - ms(1)), gap));
        assert!(may_fire(3, Some(FRAME_DUE), Some(FRAME_DUE), gap));
    }
}
