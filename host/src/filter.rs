//! Tunable filters the host drives: the bispectral rig's liquid-crystal filters on the light
//! and on the camera (thesis section 4.3) are serial instruments of their own, not controller
//! peripherals. A small trait ([`TunableFilter`]), one implementation over a serial port that
//! speaks the command set the rig file gives ([`SerialFilter`], [`CommandSet`]), and
//! [`FilterPreparation`], which tunes a step's `meta.host` wavelengths through them before the
//! step's sequence runs (and hands anything else the step asks to a person).
//!
//! No vendor's command set is built in: the public manuals of common filters were not at hand
//! to confirm one, so the strings come from the rig file (`[plan.tunable_filter]`: `tune`,
//! `ok`, `error`), with the defaults below documented as placeholders.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use crate::acquire::{step_requests, StepPreparation};
use crate::plan::Step;

/// What a filter is told and what it answers.
#[derive(Debug, Clone, PartialEq)]
pub struct CommandSet {
    /// Sent to tune; `{nm}` is replaced by the wavelength with `decimals` decimals.
    pub tune: String,
    /// Decimals of the wavelength in `tune`.
    pub decimals: usize,
    /// The start of the reply that means "tuned".
    pub ok: String,
    /// The start of a reply that means the filter refused (the rest is its words).
    pub error: String,
    /// How long to wait for the reply.
    pub timeout: Duration,
    /// How long the liquid crystal takes to settle after the reply.
    pub settle: Duration,
    /// The wavelengths it covers, nm.
    pub range_nm: (f64, f64),
}

impl Default for CommandSet {
    /// Placeholders: `W {nm}` and a carriage return, `OK` or `ERR …`, 1 s, 50 ms settling,
    /// 400–720 nm.
    fn default() -> Self {
        CommandSet {
            tune: "W {nm}\r".into(),
            decimals: 1,
            ok: "OK".into(),
            error: "ERR".into(),
            timeout: Duration::from_secs(1),
            settle: Duration::from_millis(50),
            range_nm: (400.0, 720.0),
        }
    }
}

/// Why a filter did not tune.
#[derive(Debug)]
pub enum FilterError {
    /// Outside the filter's range: nothing was sent.
    OutOfRange {
        /// The filter.
        filter: String,
        /// Asked for, nm.
        nm: f64,
        /// Its range, nm.
        range: (f64, f64),
    },
    /// The filter answered with an error.
    Refused {
        /// The filter.
        filter: String,
        /// Asked for, nm.
        nm: f64,
        /// Its reply.
        reply: String,
    },
    /// No complete answer in time.
    Timeout {
        /// The filter.
        filter: String,
        /// Asked for, nm.
        nm: f64,
        /// What arrived, if anything.
        partial: String,
    },
    /// The port failed.
    Io {
        /// The filter.
        filter: String,
        /// The error.
        error: io::Error,
    },
}

impl std::fmt::Display for FilterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FilterError::OutOfRange { filter, nm, range } => {
                write!(f, "{filter}: {nm} nm is outside its range {}–{} nm", range.0, range.1)
            }
            FilterError::Refused { filter, nm, reply } => {
                write!(f, "{filter}: refused {nm} nm: {reply:?}")
            }
            FilterError::Timeout { filter, nm, partial } => write!(
                f,
                "{filter}: no answer to {nm} nm in time (received {partial:?}); check its port, power and \
                 the command strings in [plan.tunable_filter]"
            ),
            FilterError::Io { filter, error } => write!(f, "{filter}: {error}"),
        }
    }
}

impl std::error::Error for FilterError {}

/// A filter the host tunes.
pub trait TunableFilter: Send {
    /// Its name, for messages.
    fn name(&self) -> &str;
    /// Tunes to `nm`; returns once the filter has answered and settled.
    fn tune(&mut self, nm: f64) -> Result<(), FilterError>;
}

/// A filter on a serial port (or anything that reads and writes like one).
pub struct SerialFilter<P: Read + Write + Send> {
    name: String,
    port: P,
    commands: CommandSet,
}

impl SerialFilter<Box<dyn serialport::SerialPort>> {
    /// Opens `path` at `baud`.
    pub fn open(name: &str, path: &str, baud: u32, commands: CommandSet) -> Result<Self, FilterError> {
        let port = serialport::new(path, baud).timeout(Duration::from_millis(20)).open().map_err(|e| {
            FilterError::Io { filter: name.to_string(), error: io::Error::other(format!("{path}: {e}")) }
        })?;
        Ok(SerialFilter::new(name, port, commands))
    }
}

impl<P: Read + Write + Send> SerialFilter<P> {
    /// A filter named `name` on `port`.
    pub fn new(name: &str, port: P, commands: CommandSet) -> Self {
        SerialFilter { name: name.to_string(), port, commands }
    }

    fn io(&self, error: io::Error) -> FilterError {
        FilterError::Io { filter: self.name.clone(), error }
    }
}

impl<P: Read + Write + Send> TunableFilter for SerialFilter<P> {
    fn name(&self) -> &str {
        &self.name
    }

    fn tune(&mut self, nm: f64) -> Result<(), FilterError> {
        let c = &self.commands;
        if !(c.range_nm.0..=c.range_nm.1).contains(&nm) {
            return Err(FilterError::OutOfRange { filter: self.name.clone(), nm, range: c.range_nm });
        }
        let text = format!("{nm:.*}", c.decimals);
        let command = c.tune.replace("{nm}", &text);
        self.port.write_all(command.as_bytes()).map_err(|e| self.io(e))?;
        self.port.flush().map_err(|e| self.io(e))?;
        // One reply line, ended by a carriage return or a line feed.
        let deadline = Instant::now() + self.commands.timeout;
        let mut line = Vec::new();
        let mut byte = [0u8; 1];
        loop {
            if Instant::now() > deadline {
                let partial = String::from_utf8_lossy(&line).into_owned();
                return Err(FilterError::Timeout { filter: self.name.clone(), nm, partial });
            }
            match self.port.read(&mut byte) {
                Ok(0) => continue,
                Ok(_) if byte[0] == b'\r' || byte[0] == b'\n' => {
                    if line.is_empty() {
                        continue;
                    }
                    break;
                }
                Ok(_) => line.push(byte[0]),
                Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock) => continue,
                Err(e) => return Err(self.io(e)),
            }
        }
        let reply = String::from_utf8_lossy(&line).trim().to_string();
        let c = &self.commands;
        if reply.starts_with(&c.ok) {
            std::thread::sleep(c.settle);
            Ok(())
        } else {
            let reply = reply.strip_prefix(&c.error).map_or(reply.clone(), |r| r.trim().to_string());
            Err(FilterError::Refused { filter: self.name.clone(), nm, reply })
        }
    }
}

/// Filters by the `meta.host` key they tune (`light_filter_nm`, `camera_filter_nm`).
pub type Filters = Vec<(String, Box<dyn TunableFilter>)>;

/// Sets a step's `meta.host` wavelengths (`light_filter_nm`, `camera_filter_nm`, …) through the
/// filters named by those keys, then hands what is left (a person's action, a setting with no
/// filter) to `rest`. The journal's `StepPrepared.by` is `instruments`, or `rest`'s word when
/// it did anything.
pub struct FilterPreparation {
    /// `(meta.host key, filter)`.
    pub filters: Filters,
    /// What handles the other requests.
    pub rest: Box<dyn StepPreparation>,
}

impl StepPreparation for FilterPreparation {
    fn prepare(&mut self, step: &Step, requests: &[String]) -> Result<String, String> {
        let host = step.meta.get("host").and_then(|h| h.as_object());
        let mut rest = step.clone();
        if let Some(host) = host {
            let mut left = host.clone();
            for (key, filter) in &mut self.filters {
                let Some(nm) = host.get(key.as_str()).and_then(|v| v.as_f64()) else { continue };
                filter.tune(nm).map_err(|e| format!("step {} ({}): {e}", step.id, step.name))?;
                left.remove(key.as_str());
            }
            rest.meta["host"] = serde_json::Value::Object(left);
        }
        let left = step_requests(&rest);
        if left.is_empty() {
            let _ = requests;
            return Ok("instruments".into());
        }
        self.rest.prepare(&rest, &left)
    }
}

/// The filters `[plan.tunable_filter]` names ports for: `light_port` tunes `light_filter_nm`,
/// `camera_port` tunes `camera_filter_nm`; `baud` (9600), `range_nm` (or `light_range_nm`,
/// `camera_range_nm`), `settle_ms` and the command set (`tune`, `decimals`, `ok`, `error`,
/// `timeout_ms`) apply to both. None when no
/// port is given (a person, or the virtual rig's instruments, set the filters).
pub fn from_rig(rig: &crate::rigfile::RigFile) -> Result<Filters, crate::rigfile::RigError> {
    let Some(t) = rig.plan.get("tunable_filter").and_then(|v| v.as_table()) else { return Ok(Vec::new()) };
    let key = |k: &str| format!("plan.tunable_filter.{k}");
    let num = |k: &str| -> Result<Option<f64>, crate::rigfile::RigError> {
        match t.get(k) {
            None => Ok(None),
            Some(v) => v
                .as_float()
                .or_else(|| v.as_integer().map(|i| i as f64))
                .map(Some)
                .ok_or_else(|| rig.error(&key(k), "must be a number")),
        }
    };
    let text = |k: &str| -> Result<Option<String>, crate::rigfile::RigError> {
        match t.get(k) {
            None => Ok(None),
            Some(v) => {
                v.as_str().map(|s| Some(s.to_string())).ok_or_else(|| rig.error(&key(k), "must be a string"))
            }
        }
    };
    let range = |k: &str| -> Result<Option<(f64, f64)>, crate::rigfile::RigError> {
        let Some(r) = t.get(k) else { return Ok(None) };
        let bad = || rig.error(&key(k), "must be [from, to] in nm");
        let a = r.as_array().filter(|a| a.len() == 2).ok_or_else(bad)?;
        let v = |x: &toml::Value| x.as_float().or_else(|| x.as_integer().map(|i| i as f64)).ok_or_else(bad);
        Ok(Some((v(&a[0])?, v(&a[1])?)))
    };
    let mut c = CommandSet::default();
    if let Some(r) = range("range_nm")? {
        c.range_nm = r;
    }
    if let Some(ms) = num("settle_ms")? {
        c.settle = Duration::from_secs_f64(ms.max(0.0) / 1e3);
    }
    if let Some(ms) = num("timeout_ms")? {
        c.timeout = Duration::from_secs_f64(ms.max(0.0) / 1e3);
    }
    if let Some(d) = num("decimals")? {
        c.decimals = d.clamp(0.0, 6.0) as usize;
    }
    if let Some(s) = text("tune")? {
        if !s.contains("{nm}") {
            return Err(rig.error(&key("tune"), "must contain `{nm}`, where the wavelength goes"));
        }
        c.tune = s;
    }
    if let Some(s) = text("ok")? {
        c.ok = s;
    }
    if let Some(s) = text("error")? {
        c.error = s;
    }
    let baud = num("baud")?.unwrap_or(9600.0) as u32;
    let mut out: Filters = Vec::new();
    for (port_key, meta_key, name) in [
        ("light_port", "light_filter_nm", "light filter"),
        ("camera_port", "camera_filter_nm", "camera filter"),
    ] {
        if let Some(port) = text(port_key)? {
            // `light_range_nm` / `camera_range_nm` where the two filters differ.
            let mut c = c.clone();
            if let Some(r) = range(&port_key.replace("port", "range_nm"))? {
                c.range_nm = r;
            }
            let f = SerialFilter::open(name, &port, baud, c)
                .map_err(|e| rig.error(&key(port_key), e.to_string()))?;
            out.push((meta_key.to_string(), Box::new(f)));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A port whose replies are scripted and whose writes are kept.
    struct Script {
        replies: io::Cursor<Vec<u8>>,
        written: Vec<u8>,
    }

    impl Read for Script {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            match self.replies.read(buf)? {
                0 => Err(io::ErrorKind::TimedOut.into()),
                n => Ok(n),
            }
        }
    }

    impl Write for Script {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.written.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    fn filter(replies: &str) -> SerialFilter<Script> {
        let commands = CommandSet {
            settle: Duration::ZERO,
            timeout: Duration::from_millis(50),
            ..CommandSet::default()
        };
        SerialFilter::new(
            "camera filter",
            Script { replies: io::Cursor::new(replies.as_bytes().to_vec()), written: Vec::new() },
            commands,
        )
    }

    #[test]
    fn tuning_sends_the_command_and_reads_the_answer() {
        let mut f = filter("\r\nOK\rERR 3 not ready\r");
        f.tune(550.0).unwrap();
        assert_eq!(f.port.written, b"W 550.0\r");
        let e = f.tune(551.25).unwrap_err();
        assert!(matches!(&e, FilterError::Refused { reply, .. } if reply == "3 not ready"), "{e}");
        assert_eq!(&f.port.written[8..], b"W 551.2\r");
        let e = f.tune(560.0).unwrap_err();
        assert!(matches!(e, FilterError::Timeout { .. }), "{e}");
        assert!(e.to_string().contains("[plan.tunable_filter]"));
        let e = f.tune(800.0).unwrap_err();
        assert!(e.to_string().contains("800 nm is outside its range 400–720 nm"), "{e}");
        assert_eq!(f.port.written.len(), 24, "nothing sent for a wavelength out of range");
    }
}
