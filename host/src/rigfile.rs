//! The rig description file: a lab's rig in TOML — wiring, units, limits, cameras and where
//! their frames come from.
//!
//! [`RigFile::parse`] reads a file in human units (millimetres, degrees, µs/ms/s as each key's
//! suffix says) and checks everything that does not depend on the device: key names, types,
//! enum strings, duplicate indexes, signs. [`RigFile::config_items`] converts it to the
//! device's integer [`ConfigItem`]s for the device's tick rate and checks them with
//! [`ConfigItem::validate`], the same validation the firmware runs. Every error names the file,
//! the line and the key (`docs/rigs/lls-gantry.toml:25: stepper[0].max_speed: must be at most
//! 6250 mm/s (500000 steps/s at 80 steps/mm)`), with the valid values where that helps.
//!
//! Conversions are exact: a number is taken as the decimal written in the file (its shortest
//! round-trip representation), scaled with integer arithmetic and rounded to the nearest
//! integer, ties away from zero. Times: `ticks = round(value · tick_hz / unit)`. Stepper
//! quantities go through millionths of a unit and the axis' [`Ratio`]
//! ([`Ratio::steps_from_micro`]), so a position planned in millimetres lands on the same step
//! as the same number in the file.
//!
//! `docs/rigs/README.md` documents every key; `docs/rigs/*.toml` are worked examples.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use lightrig_protocol::config::{
    AxisKind, CameraConfig, ConfigError, ConfigField, ConfigItem, DacKind, FilterWheelConfig, GalvoAxis,
    GalvoConfig, Homing, HomingMode, Input, InvalidReason, LaserConfig, Polarity, Ratio, SafetyConfig,
    StepRange, StepperConfig, VoiceCoilConfig, Xy, HEARTBEAT_RANGE_MS, SAMPLE_RATE_RANGE, WAVELENGTH_RANGE,
};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{
    MAX_CAMERAS, MAX_FILTER_SLOTS, MAX_FILTER_WHEELS, MAX_GALVOS, MAX_LASERS, MAX_STEPPERS, MAX_VOICE_COILS,
};
use serde::Deserialize;
use toml::de::{DeTable, DeValue};

/// Baud rate of `serial:PATH` without `@BAUD` (CDC-ACM ignores it).
pub const DEFAULT_BAUD: u32 = 115_200;

/// A rig file that was refused: where, which key, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RigError {
    /// The rig file.
    pub path: PathBuf,
    /// 1-based line of the key (or of its table when the key is missing), if known.
    pub line: Option<usize>,
    /// Dotted key, `stepper[0].max_speed` (array index = position in the file); empty for
    /// errors about the file as a whole.
    pub key: String,
    /// What is wrong, and what to do where that is not obvious.
    pub message: String,
}

impl fmt::Display for RigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.path.display())?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        f.write_str(": ")?;
        if !self.key.is_empty() {
            write!(f, "{}: ", self.key)?;
        }
        f.write_str(&self.message)
    }
}

impl std::error::Error for RigError {}

/// The acquisition method the rig is built for; selects the planner.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// `disco`: laser-scanned translucent-object acquisition (galvos, lasers, turntable).
    Disco,
    /// `fluorescent-immersion`: fluorescent immersion range scanning (laser sheet, turntable).
    FluorescentImmersion,
    /// `bispectral`: bispectral reflectance and reradiation (gonioreflectometer).
    Bispectral,
    /// `linear-light-source`: linear light source reflectometry (gantry, light tube).
    LinearLightSource,
    /// `brdf-display`: the voice-coil-driven BRDF display.
    BrdfDisplay,
}

const METHODS: &[(&str, Method)] = &[
    ("disco", Method::Disco),
    ("fluorescent-immersion", Method::FluorescentImmersion),
    ("bispectral", Method::Bispectral),
    ("linear-light-source", Method::LinearLightSource),
    ("brdf-display", Method::BrdfDisplay),
];

impl Method {
    /// The name used in rig files.
    pub fn as_str(self) -> &'static str {
        METHODS.iter().find(|(_, m)| *m == self).map_or("", |(s, _)| s)
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How to reach the device (`[device] connect`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Connect {
    /// `"virtual"`: the firmware in this process on a simulated board.
    Virtual,
    /// `"serial:PATH"` or `"serial:PATH@BAUD"`.
    Serial {
        /// Port path (`/dev/ttyACM0`, `COM3`).
        port: String,
        /// Baud rate ([`DEFAULT_BAUD`] when not given).
        baud: u32,
    },
    /// `"usb"`: the first lightrig device found on USB.
    Usb,
}

/// Range and calibration of one galvo axis, as written.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GalvoAxisSpec {
    /// Lowest code.
    pub min_code: u16,
    /// Highest code.
    pub max_code: u16,
    /// Code of zero deflection.
    pub zero_code: u16,
    /// Optical deflection per code, µrad (negative: mirrored); sent as whole nanoradians.
    pub urad_per_code: f64,
}

/// A galvo pair (`[[galvo]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct Galvo {
    /// Device index.
    pub galvo: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// Converter.
    pub dac: DacKind,
    /// X axis.
    pub x: GalvoAxisSpec,
    /// Y axis.
    pub y: GalvoAxisSpec,
    /// Park position `[x, y]` in codes (defaults to the zero codes).
    pub park: [u16; 2],
    /// Settling time after a jump, µs.
    pub settle_us: f64,
}

/// A laser channel (`[[laser]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct Laser {
    /// Device channel.
    pub channel: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// What the light does for the rig's planner (`role`): a pass finds its light by role,
    /// never by the spelling of a name.
    pub role: Option<LaserRole>,
    /// Nominal wavelength, nm.
    pub wavelength_nm: u16,
    /// Warm-up until the output is stable, ms.
    pub warmup_ms: f64,
    /// Longest continuous on-time, s.
    pub max_on_s: f64,
    /// Level of the enable output that lets light out.
    pub enable: Polarity,
    /// Interlock input.
    pub interlock: Input,
}

/// A light's job in a linear-light-source rig (`[[laser]] role`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LaserRole {
    /// The linear light source of the reflectance passes.
    Tube,
    /// The laser stripe of the height pass.
    Stripe,
    /// The light under the sample of the backlit (translucency) pass.
    Backlight,
}

impl LaserRole {
    /// The role as the rig file spells it.
    pub fn key(self) -> &'static str {
        name_of(LASER_ROLES, self)
    }
}

/// Homing of a stepper axis, in the axis' units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingSpec {
    /// What to seek.
    pub mode: HomingMode,
    /// Seek speed, units/s (0 when `mode` is `None`).
    pub speed: f64,
    /// Distance to back off the switch, units.
    pub backoff: f64,
    /// Position assigned once homed, units.
    pub position: f64,
}

/// A stepper axis (`[[stepper]]`): a gantry (mm) or a turntable (degrees).
#[derive(Debug, Clone, PartialEq)]
pub struct Stepper {
    /// Device axis.
    pub axis: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// Linear (mm) or rotary (degrees).
    pub kind: AxisKind,
    /// Steps per unit, reduced.
    pub steps_per_unit: Ratio,
    /// Top speed, units/s.
    pub max_speed: f64,
    /// Acceleration, units/s².
    pub accel: f64,
    /// Soft limits `(min, max)`, units; `None` for an endless rotary axis.
    pub limits: Option<(f64, f64)>,
    /// Homing.
    pub homing: HomingSpec,
    /// Invert the direction output.
    pub invert_dir: bool,
    /// Driver-enable level.
    pub enable: Polarity,
    /// Min limit switch.
    pub limit_min: Input,
    /// Max limit switch.
    pub limit_max: Input,
    /// Index sensor.
    pub index: Input,
}

impl Stepper {
    /// The axis' unit: `mm` or `deg`.
    pub fn unit(&self) -> &'static str {
        unit_name(self.kind)
    }

    /// Steps at `value` units (exact decimal, via millionths of a unit), `None` if it does
    /// not fit. Not checked against the limits (see [`RigFile::stepper_steps`]).
    pub fn steps(&self, value: f64) -> Option<i64> {
        self.steps_per_unit.steps_from_micro(micro(value)?)
    }

    /// Units at `steps` (nearest millionth).
    pub fn units(&self, steps: i64) -> Option<f64> {
        Some(self.steps_per_unit.micro_from_steps(steps)? as f64 / 1e6)
    }
}

/// A filter wheel (`[[filter_wheel]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct FilterWheel {
    /// Device index.
    pub wheel: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// Number of slots.
    pub slots: u8,
    /// Name of each slot, if the file gave `filters` (empty otherwise).
    pub filters: Vec<String>,
    /// Motor steps per wheel revolution.
    pub steps_per_rev: u32,
    /// Top speed, revolutions/s.
    pub max_speed: f64,
    /// Acceleration, revolutions/s².
    pub accel: f64,
    /// Index sensor.
    pub index: Input,
    /// Steps from the index mark to the centre of slot 0.
    pub index_offset: i32,
    /// Invert the direction output.
    pub invert_dir: bool,
    /// Driver-enable level.
    pub enable: Polarity,
}

/// A voice-coil channel (`[[voice_coil]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct VoiceCoil {
    /// Device channel.
    pub channel: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// Sample rate, Hz.
    pub sample_rate_hz: u32,
    /// Largest summed amplitude, fraction of full scale (0..=1).
    pub max_amplitude: f64,
}

/// Where a camera's frames come from (host side only; never sent to the device).
#[derive(Debug, Clone, PartialEq)]
pub enum FrameSource {
    /// Synthetic frames from the virtual rig.
    Virtual {
        /// The virtual sensor's display gamma (`source.gamma`, 1 = linear): stored values are
        /// `v^(1/gamma)`, a camera whose fits need its response (`response`).
        gamma: f64,
    },
    /// Files the camera software writes into a directory.
    Directory {
        /// The directory, relative paths resolved against the rig file's directory.
        dir: PathBuf,
        /// File name with a `{frame}` or `{frame:0N}` placeholder.
        pattern: String,
    },
    /// A GenICam camera (GigE Vision, USB3 Vision) read through Aravis.
    Genicam(GenicamSource),
}

/// A GenICam camera's settings (`source = { kind = "genicam", … }`).
#[derive(Debug, Clone, PartialEq)]
pub struct GenicamSource {
    /// The camera: its address (`127.0.0.1`), or its Aravis id (`Vendor-Model-Serial`).
    pub address: String,
    /// `"software"`: the host fires a software trigger for each trigger the controller reports
    /// (a camera without its trigger line wired, or Aravis's fake camera); else the camera's
    /// trigger line wired to the controller's trigger output, e.g. `"Line0"`.
    pub trigger: String,
    /// Trigger activation for a line trigger (`RisingEdge`, `FallingEdge`, …); `None`: the
    /// camera's own setting.
    pub activation: Option<String>,
    /// Pixel format (`Mono8`, `Mono16`, …); `None`: the camera's own setting.
    pub pixel_format: Option<String>,
    /// Exposure, µs; `None`: the camera's own setting (with a line trigger in `TriggerWidth`
    /// mode the pulse sets it).
    pub exposure_us: Option<f64>,
    /// Stream buffers queued at once.
    pub buffers: u32,
}

impl FrameSource {
    /// Path of frame `frame`, for a directory source.
    pub fn frame_path(&self, frame: u64) -> Option<PathBuf> {
        match self {
            FrameSource::Virtual { .. } | FrameSource::Genicam(_) => None,
            FrameSource::Directory { dir, pattern } => {
                Some(dir.join(crate::frames::Pattern::parse(pattern).ok()?.name_of(frame)))
            }
        }
    }
}

/// A camera trigger output (`[[camera]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Device index.
    pub camera: u8,
    /// Host-side name.
    pub name: Option<String>,
    /// Default trigger pulse width, µs.
    pub pulse_us: f64,
    /// Trigger level.
    pub polarity: Polarity,
    /// Exposure-active (strobe) input.
    pub exposure_input: Input,
    /// Shortest time between two triggers, µs.
    pub min_interval_us: f64,
    /// Where the frames come from.
    pub source: FrameSource,
    /// The camera's response curve (`response`, `lightrig hdr calibrate`'s output), relative
    /// paths resolved against the rig file's directory; `None`: a linear camera.
    pub response: Option<PathBuf>,
}

/// Device-wide safety settings (`[safety]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Safety {
    /// Heartbeat timeout, ms.
    pub heartbeat_timeout_ms: f64,
}

/// A parsed rig file.
#[derive(Debug, Clone, PartialEq)]
pub struct RigFile {
    /// Where it was read from (used in every error).
    pub path: PathBuf,
    /// `[rig] name`.
    pub name: String,
    /// `[rig] description`.
    pub description: Option<String>,
    /// `[rig] method`.
    pub method: Method,
    /// `[device] connect`.
    pub connect: Connect,
    /// `[[galvo]]` tables, in file order.
    pub galvos: Vec<Galvo>,
    /// `[[laser]]` tables, in file order.
    pub lasers: Vec<Laser>,
    /// `[[stepper]]` tables, in file order.
    pub steppers: Vec<Stepper>,
    /// `[[filter_wheel]]` tables, in file order.
    pub filter_wheels: Vec<FilterWheel>,
    /// `[[voice_coil]]` tables, in file order.
    pub voice_coils: Vec<VoiceCoil>,
    /// `[[camera]]` tables, in file order.
    pub cameras: Vec<Camera>,
    /// `[safety]`; the device keeps its default heartbeat timeout (1 s) without it.
    pub safety: Option<Safety>,
    /// `[plan]`: free-form, method-specific host settings for the planners (not checked here).
    pub plan: toml::Table,
    /// Line of every key path in the file (`stepper[0].limits[1]`), for errors.
    lines: BTreeMap<String, usize>,
}

// ---------------------------------------------------------------------------------------------
// The file as serde sees it.

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRig {
    rig: RawRigSection,
    device: Option<RawDevice>,
    safety: Option<RawSafety>,
    #[serde(default)]
    galvo: Vec<RawGalvo>,
    #[serde(default)]
    laser: Vec<RawLaser>,
    #[serde(default)]
    stepper: Vec<RawStepper>,
    #[serde(default)]
    filter_wheel: Vec<RawFilterWheel>,
    #[serde(default)]
    voice_coil: Vec<RawVoiceCoil>,
    #[serde(default)]
    camera: Vec<RawCamera>,
    #[serde(default)]
    plan: toml::Table,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRigSection {
    name: String,
    method: String,
    description: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDevice {
    connect: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSafety {
    heartbeat_timeout_ms: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGalvoAxis {
    min_code: i64,
    max_code: i64,
    zero_code: i64,
    urad_per_code: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGalvo {
    galvo: i64,
    name: Option<String>,
    dac: String,
    x: RawGalvoAxis,
    y: RawGalvoAxis,
    park: Option<Vec<i64>>,
    settle_us: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLaser {
    channel: i64,
    name: Option<String>,
    role: Option<String>,
    wavelength_nm: i64,
    #[serde(default)]
    warmup_ms: f64,
    max_on_s: f64,
    enable: Option<String>,
    interlock: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHoming {
    mode: String,
    speed: Option<f64>,
    #[serde(default)]
    backoff: f64,
    #[serde(default)]
    position: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStepper {
    axis: i64,
    name: Option<String>,
    kind: String,
    steps_per_unit: toml::Value,
    max_speed: f64,
    accel: f64,
    limits: Option<Vec<f64>>,
    homing: Option<RawHoming>,
    #[serde(default)]
    invert_dir: bool,
    enable: Option<String>,
    limit_min: Option<String>,
    limit_max: Option<String>,
    index: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFilterWheel {
    wheel: i64,
    name: Option<String>,
    slots: Option<i64>,
    filters: Option<Vec<String>>,
    steps_per_rev: i64,
    max_speed: f64,
    accel: f64,
    index: String,
    #[serde(default)]
    index_offset: i64,
    #[serde(default)]
    invert_dir: bool,
    enable: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawVoiceCoil {
    channel: i64,
    name: Option<String>,
    sample_rate_hz: i64,
    max_amplitude: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSource {
    kind: String,
    path: Option<String>,
    pattern: Option<String>,
    gamma: Option<f64>,
    address: Option<String>,
    trigger: Option<String>,
    activation: Option<String>,
    pixel_format: Option<String>,
    exposure_us: Option<f64>,
    buffers: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    camera: i64,
    name: Option<String>,
    pulse_us: f64,
    polarity: Option<String>,
    exposure_input: Option<String>,
    #[serde(default)]
    min_interval_us: f64,
    source: Option<RawSource>,
    response: Option<String>,
}

// ---------------------------------------------------------------------------------------------
// Enum strings.

const POLARITIES: &[(&str, Polarity)] = &[("high", Polarity::ActiveHigh), ("low", Polarity::ActiveLow)];
const INPUTS: &[(&str, Input)] = &[
    ("high", Input::Wired(Polarity::ActiveHigh)),
    ("low", Input::Wired(Polarity::ActiveLow)),
    ("unused", Input::Unused),
];
const LASER_ROLES: &[(&str, LaserRole)] =
    &[("tube", LaserRole::Tube), ("stripe", LaserRole::Stripe), ("backlight", LaserRole::Backlight)];
const DACS: &[(&str, DacKind)] = &[
    ("dac8563", DacKind::Dac8563),
    ("ad5689", DacKind::Ad5689),
    ("mcu", DacKind::McuDac),
    ("xy2-100", DacKind::Xy2_100),
];
const AXIS_KINDS: &[(&str, AxisKind)] = &[("linear", AxisKind::Linear), ("rotary", AxisKind::Rotary)];
const HOMING_MODES: &[(&str, HomingMode)] = &[
    ("min", HomingMode::ToMinLimit),
    ("max", HomingMode::ToMaxLimit),
    ("index", HomingMode::ToIndex),
    ("none", HomingMode::None),
];
const SOURCE_KINDS: &[&str] = &["directory", "virtual", "genicam"];

fn name_of<T: PartialEq + Copy>(options: &[(&'static str, T)], value: T) -> &'static str {
    options.iter().find(|(_, v)| *v == value).map_or("?", |(s, _)| s)
}

fn unit_name(kind: AxisKind) -> &'static str {
    match kind {
        AxisKind::Linear => "mm",
        AxisKind::Rotary => "deg",
    }
}

// ---------------------------------------------------------------------------------------------
// Exact decimal arithmetic.

/// The decimal a float was written as (its shortest round-trip representation) as
/// `(numerator, 10^k)`; fractional digits beyond 18 are dropped. `None` if not finite or too
/// large.
fn exact(v: f64) -> Option<(i128, i128)> {
    if !v.is_finite() {
        return None;
    }
    let s = format!("{v}"); // never in exponent notation
    let (neg, s) = match s.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, s.as_str()),
    };
    let (int, frac) = s.split_once('.').unwrap_or((s, ""));
    let frac = &frac[..frac.len().min(18)];
    if int.len() + frac.len() > 38 {
        return None;
    }
    let m: i128 = format!("{int}{frac}").parse().ok()?;
    let den = 10i128.checked_pow(frac.len() as u32)?;
    Some((if neg { -m } else { m }, den))
}

/// `num / den` rounded to the nearest integer, ties away from zero (`den > 0`).
fn div_round(num: i128, den: i128) -> i128 {
    let half = den / 2;
    if num >= 0 {
        (num + half) / den
    } else {
        (num - half) / den
    }
}

/// `round(v · mul / div)`, exact on the decimal `v` was written as.
fn scaled(v: f64, mul: i128, div: i128) -> Option<i128> {
    let (n, d) = exact(v)?;
    Some(div_round(n.checked_mul(mul)?, d.checked_mul(div)?))
}

/// Millionths of `v`.
fn micro(v: f64) -> Option<i64> {
    i64::try_from(scaled(v, 1_000_000, 1)?).ok()
}

/// A time unit: its symbol and how many make a second.
type TimeUnit = (&'static str, u32);
const US: TimeUnit = ("µs", 1_000_000);
const MS: TimeUnit = ("ms", 1_000);
const S: TimeUnit = ("s", 1);

/// Ticks for `value` in a unit with `unit_hz` units per second (µs: 1e6, ms: 1e3, s: 1).
fn ticks(value: f64, unit_hz: u32, tick_hz: u32) -> Option<u32> {
    if value < 0.0 {
        return None;
    }
    u32::try_from(scaled(value, tick_hz.into(), unit_hz.into())?).ok()
}

/// Device ticks for a duration in µs, rounded to the nearest tick; `None` if negative or
/// beyond `u32` ticks.
pub fn ticks_from_us(us: f64, tick_hz: u32) -> Option<u32> {
    ticks(us, 1_000_000, tick_hz)
}

/// Device ticks for a duration in ms (see [`ticks_from_us`]).
pub fn ticks_from_ms(ms: f64, tick_hz: u32) -> Option<u32> {
    ticks(ms, 1_000, tick_hz)
}

/// Device ticks for a duration in s (see [`ticks_from_us`]).
pub fn ticks_from_s(s: f64, tick_hz: u32) -> Option<u32> {
    ticks(s, 1, tick_hz)
}

/// Millionths as a decimal: `6250000000` → `6250`, `12500` → `0.0125`.
fn fmt_micro(m: i128) -> String {
    let sign = if m < 0 { "-" } else { "" };
    let (int, frac) = (m.unsigned_abs() / 1_000_000, m.unsigned_abs() % 1_000_000);
    if frac == 0 {
        format!("{sign}{int}")
    } else {
        let frac = format!("{frac:06}");
        format!("{sign}{int}.{}", frac.trim_end_matches('0'))
    }
}

fn fmt_ratio(r: Ratio) -> String {
    if r.den == 1 {
        r.num.to_string()
    } else {
        format!("{}/{}", r.num, r.den)
    }
}

fn gcd(mut a: u128, mut b: u128) -> u128 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Parses `"80"`, `"3200/360"`, `"200*16*90/360"`, `"a*b/c*d"`: a product of positive integers,
/// optionally divided by another product. Reduced to lowest terms.
fn parse_ratio(s: &str) -> Result<Ratio, String> {
    const FORM: &str = "write a product of positive integers, optionally divided by another, e.g. \"80\", \
                        \"3200/360\" or \"200*16*90/360\"";
    let product = |p: &str| -> Result<u128, String> {
        let mut acc: u128 = 1;
        for factor in p.split('*') {
            let f = factor.trim();
            if f.is_empty() || !f.bytes().all(|b| b.is_ascii_digit()) {
                return Err(format!("\"{s}\" is not a ratio; {FORM}"));
            }
            let v: u128 = f.parse().map_err(|_| format!("\"{s}\": factor {f} is too large"))?;
            if v == 0 {
                return Err(format!("\"{s}\" has a zero factor; steps per unit must be positive"));
            }
            acc = acc.checked_mul(v).ok_or_else(|| format!("\"{s}\" is too large"))?;
        }
        Ok(acc)
    };
    let mut parts = s.split('/');
    let num = product(parts.next().unwrap_or(""))?;
    let den = match parts.next() {
        Some(d) => product(d)?,
        None => 1,
    };
    if parts.next().is_some() {
        return Err(format!("\"{s}\" has more than one '/'; {FORM}"));
    }
    let g = gcd(num, den);
    let (num, den) = (num / g, den / g);
    match (u32::try_from(num), u32::try_from(den)) {
        (Ok(num), Ok(den)) => Ok(Ratio { num, den }),
        _ => Err(format!("\"{s}\" reduces to {num}/{den}, which does not fit in 32 bits")),
    }
}

// ---------------------------------------------------------------------------------------------
// Spans, lines and key paths.

struct Node {
    path: String,
    key: Range<usize>,
    value: Range<usize>,
    line: usize,
}

/// Byte offset to 1-based line number.
struct Lines(Vec<usize>);

impl Lines {
    fn new(text: &str) -> Self {
        Lines(text.bytes().enumerate().filter(|(_, b)| *b == b'\n').map(|(i, _)| i).collect())
    }

    fn at(&self, offset: usize) -> usize {
        self.0.partition_point(|&nl| nl < offset) + 1
    }
}

fn join(prefix: &str, key: &str) -> String {
    let bare = !key.is_empty() && key.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    let key = if bare { key.to_string() } else { format!("{key:?}") };
    if prefix.is_empty() {
        key
    } else {
        format!("{prefix}.{key}")
    }
}

fn index_table(t: &DeTable<'_>, prefix: &str, lines: &Lines, out: &mut Vec<Node>) {
    for (k, v) in t.iter() {
        let path = join(prefix, k.get_ref());
        out.push(Node { path: path.clone(), key: k.span(), value: v.span(), line: lines.at(k.span().start) });
        index_value(v.get_ref(), &path, lines, out);
    }
}

fn index_value(v: &DeValue<'_>, path: &str, lines: &Lines, out: &mut Vec<Node>) {
    match v {
        DeValue::Table(t) => index_table(t, path, lines, out),
        DeValue::Array(a) => {
            for (i, e) in a.iter().enumerate() {
                let p = format!("{path}[{i}]");
                out.push(Node {
                    path: p.clone(),
                    key: e.span(),
                    value: e.span(),
                    line: lines.at(e.span().start),
                });
                index_value(e.get_ref(), &p, lines, out);
            }
        }
        _ => {}
    }
}

/// The key path an error span points at: a key, a value, or a table header.
fn locate<'a>(nodes: &'a [Node], span: &Range<usize>) -> Option<&'a Node> {
    if let Some(n) = nodes.iter().find(|n| n.key == *span) {
        return Some(n);
    }
    let deepest = |a: &&Node, b: &&Node| a.path.len().cmp(&b.path.len());
    if let Some(n) = nodes.iter().filter(|n| n.value == *span).max_by(deepest) {
        return Some(n);
    }
    nodes
        .iter()
        .filter(|n| n.value.start <= span.start && span.end <= n.value.end)
        .min_by_key(|n| (n.value.len(), usize::MAX - n.path.len()))
}

/// Backquoted names in a serde message: "unknown field `x`, expected one of `a`, `b`".
fn backquoted(s: &str) -> Vec<&str> {
    s.split('`').skip(1).step_by(2).collect()
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let cur = row[j + 1];
            row[j + 1] = (prev + usize::from(ca != *cb)).min(row[j] + 1).min(cur + 1);
            prev = cur;
        }
    }
    row[b.len()]
}

/// The closest candidate, if it is close enough to be a likely typo.
fn suggest<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let word = word.to_ascii_lowercase();
    candidates
        .into_iter()
        .map(|c| {
            let lower = c.to_ascii_lowercase();
            let d = edit_distance(&word, &lower);
            // "max_speed_mm_s" for "max_speed", "active-low" for "low": one word inside the other.
            let inside = word.len().min(lower.len()) >= 3 && (word.contains(&lower) || lower.contains(&word));
            (if inside { d.min(1) } else { d }, c)
        })
        .filter(|(d, c)| *d <= (c.len() / 3).max(1))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// Plain words for serde's type names.
fn type_words(t: &str) -> String {
    let t = t.trim();
    match t {
        "i64" | "u8" | "u16" | "u32" | "i32" | "u64" => "an integer".into(),
        "f64" | "f32" => "a number".into(),
        "a sequence" => "an array".into(),
        "a map" => "a table".into(),
        "a boolean" | "a string" => t.into(),
        _ if t.starts_with("struct ") => "a table".into(),
        _ if t.starts_with("any valid TOML value") => "a value".into(),
        _ => t.into(),
    }
}

fn quoted_list<'a>(values: impl IntoIterator<Item = &'a str>) -> String {
    values.into_iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ")
}

/// A short reminder of what a required key of table `table` holds.
fn key_hint(table: &str, field: &str) -> Option<String> {
    let one_of = |values: &[&str]| format!("one of {}", quoted_list(values.iter().copied()));
    fn names<T>(options: &[(&'static str, T)]) -> Vec<&'static str> {
        options.iter().map(|(s, _)| *s).collect()
    }
    Some(match field {
        "rig" => "[rig] with name and method".into(),
        "name" => "a name for the rig".into(),
        "method" => one_of(&names(METHODS)),
        "galvo" => "the galvo pair's device index".into(),
        "channel" => "the device channel".into(),
        "axis" => "the device axis".into(),
        "wheel" => "the device filter wheel index".into(),
        "camera" => "the device trigger output".into(),
        "dac" => one_of(&names(DACS)),
        "x" | "y" => "{ min_code, max_code, zero_code, urad_per_code }".into(),
        "min_code" | "max_code" | "zero_code" => "a DAC code".into(),
        "urad_per_code" => "optical deflection per code in µrad".into(),
        "settle_us" => "settling time after a jump in µs".into(),
        "wavelength_nm" => "nominal wavelength in nm".into(),
        "max_on_s" => "longest continuous on-time in s".into(),
        "interlock" | "index" => one_of(&names(INPUTS)),
        "kind" if table.ends_with("source") => one_of(SOURCE_KINDS),
        "kind" => one_of(&names(AXIS_KINDS)),
        "steps_per_unit" => "steps per mm or degree, e.g. \"80\" or \"200*16*90/360\"".into(),
        "max_speed" if table.starts_with("filter_wheel") => "top speed in rev/s".into(),
        "max_speed" => "top speed in mm/s or deg/s".into(),
        "accel" if table.starts_with("filter_wheel") => "acceleration in rev/s²".into(),
        "accel" => "acceleration in mm/s² or deg/s²".into(),
        "mode" => one_of(&names(HOMING_MODES)),
        "steps_per_rev" => "motor steps per wheel revolution".into(),
        "sample_rate_hz" => "output sample rate in Hz".into(),
        "max_amplitude" => "largest amplitude, 0.0..=1.0 of full scale".into(),
        "pulse_us" => "trigger pulse width in µs".into(),
        "response" => "the camera's response file from `lightrig hdr calibrate`".into(),
        "gamma" => "the virtual camera's display gamma, 1 = linear".into(),
        "address" => "the GenICam camera's address or Aravis id".into(),
        "trigger" => "\"software\" or the camera's trigger line, e.g. \"Line0\"".into(),
        "buffers" => "stream buffers queued at once".into(),
        "heartbeat_timeout_ms" => "heartbeat timeout in ms".into(),
        _ => return None,
    })
}

/// A device count in words: "the device has only 3 lasers (channels 0..=2)".
fn no_such(count: u8, singular: &str, plural: &str, index: &str, indexes: &str) -> String {
    match count {
        0 => format!("the device has no {plural}; remove this table or connect a device that has {plural}"),
        1 => format!("the device has only 1 {singular} ({index} 0)"),
        n => format!("the device has only {n} {plural} ({indexes} 0..={})", n - 1),
    }
}

// ---------------------------------------------------------------------------------------------
// Building a RigFile.

struct Cx<'a> {
    path: &'a Path,
    lines: &'a BTreeMap<String, usize>,
}

/// Line of `key`, or of the nearest enclosing key that is in the file.
fn line_of(lines: &BTreeMap<String, usize>, key: &str) -> Option<usize> {
    let mut k = key;
    loop {
        if let Some(&l) = lines.get(k) {
            return Some(l);
        }
        let cut = k.rfind(['.', '['])?;
        k = &k[..cut];
    }
}

impl Cx<'_> {
    fn err(&self, key: &str, message: impl Into<String>) -> RigError {
        RigError {
            path: self.path.to_path_buf(),
            line: line_of(self.lines, key),
            key: key.to_string(),
            message: message.into(),
        }
    }

    fn choice<T: Copy>(&self, key: &str, value: &str, options: &[(&'static str, T)]) -> Result<T, RigError> {
        if let Some((_, v)) = options.iter().find(|(s, _)| *s == value) {
            return Ok(*v);
        }
        Err(self.err(key, unknown_value(value, options.iter().map(|(s, _)| *s))))
    }

    fn opt_choice<T: Copy>(
        &self,
        key: &str,
        value: Option<&str>,
        default: T,
        options: &[(&'static str, T)],
    ) -> Result<T, RigError> {
        value.map_or(Ok(default), |v| self.choice(key, v, options))
    }

    /// A device index below the protocol's maximum.
    fn index(&self, key: &str, value: i64, max: usize, what: &str) -> Result<u8, RigError> {
        if value < 0 {
            return Err(self.err(key, "must not be negative"));
        }
        if value >= max as i64 {
            return Err(
                self.err(key, format!("must be at most {}: the protocol has at most {max} {what}", max - 1))
            );
        }
        Ok(value as u8)
    }

    fn int(&self, key: &str, value: i64, lo: i64, hi: i64) -> Result<i64, RigError> {
        if value < lo {
            return Err(self.err(key, format!("must be at least {lo}")));
        }
        if value > hi {
            return Err(self.err(key, format!("must be at most {hi}")));
        }
        Ok(value)
    }

    fn finite(&self, key: &str, value: f64) -> Result<f64, RigError> {
        if value.is_finite() {
            Ok(value)
        } else {
            Err(self.err(key, "must be a finite number"))
        }
    }

    fn nonneg(&self, key: &str, value: f64) -> Result<f64, RigError> {
        if self.finite(key, value)? < 0.0 {
            return Err(self.err(key, "must not be negative"));
        }
        Ok(value)
    }

    fn code(&self, key: &str, value: i64) -> Result<u16, RigError> {
        if !(0..=i64::from(u16::MAX)).contains(&value) {
            return Err(self.err(key, "must be a DAC code in 0..=65535"));
        }
        Ok(value as u16)
    }
}

fn unknown_value<'a>(value: &str, options: impl Iterator<Item = &'a str> + Clone) -> String {
    let list = quoted_list(options.clone());
    match suggest(value, options) {
        Some(s) => format!("unknown value \"{value}\"; did you mean \"{s}\"? Valid values: {list}"),
        None => format!("unknown value \"{value}\"; valid values: {list}"),
    }
}

/// Refuses a second entry with the same device index or the same name.
fn no_duplicates(
    cx: &Cx<'_>,
    kind: &str,
    field: &str,
    entries: &[(u8, Option<&str>)],
) -> Result<(), RigError> {
    let mut seen: HashMap<u8, usize> = HashMap::new();
    let mut names: HashMap<&str, usize> = HashMap::new();
    for (i, (index, name)) in entries.iter().enumerate() {
        if let Some(first) = seen.insert(*index, i) {
            let first_key = format!("{kind}[{first}]");
            let line = line_of(cx.lines, &first_key).map_or(String::new(), |l| format!(" at line {l}"));
            return Err(cx.err(
                &format!("{kind}[{i}].{field}"),
                format!(
                    "{field} {index} is already configured by {first_key}{line}; each {field} may appear \
                     once"
                ),
            ));
        }
        if let Some(name) = name {
            if let Some(first) = names.insert(name, i) {
                return Err(cx.err(
                    &format!("{kind}[{i}].name"),
                    format!("name \"{name}\" is already used by {kind}[{first}]; names must be unique"),
                ));
            }
        }
    }
    Ok(())
}

/// Each role once, and only where the rig's planner gives lights roles.
fn laser_roles(cx: &Cx<'_>, method: Method, lasers: &[Laser]) -> Result<(), RigError> {
    let mut seen: HashMap<LaserRole, usize> = HashMap::new();
    for (i, l) in lasers.iter().enumerate() {
        let Some(role) = l.role else { continue };
        let key = format!("laser[{i}].role");
        if method != Method::LinearLightSource {
            return Err(cx.err(
                &key,
                "roles (tube, stripe, backlight) are for linear-light-source rigs; this rig's planner \
                 takes its lasers from [plan] by name: remove the key",
            ));
        }
        if let Some(first) = seen.insert(role, i) {
            return Err(cx.err(
                &key,
                format!("role \"{}\" is already laser[{first}]'s; each role is one laser's", role.key()),
            ));
        }
    }
    Ok(())
}

fn parse_connect(s: &str) -> Result<Connect, String> {
    const FORMS: &str = "valid values: \"virtual\", \"usb\", \"serial:PATH\" or \"serial:PATH@BAUD\" (e.g. \
                         \"serial:/dev/ttyACM0@115200\")";
    match s {
        "virtual" => return Ok(Connect::Virtual),
        "usb" => return Ok(Connect::Usb),
        _ => {}
    }
    let Some(rest) = s.strip_prefix("serial:") else {
        return Err(format!("unknown value \"{s}\"; {FORMS}"));
    };
    let (port, baud) = match rest.rsplit_once('@') {
        Some((port, baud)) => {
            let baud = baud
                .parse::<u32>()
                .ok()
                .filter(|b| *b > 0)
                .ok_or_else(|| format!("\"{baud}\" after '@' is not a baud rate; {FORMS}"))?;
            (port, baud)
        }
        None => (rest, DEFAULT_BAUD),
    };
    if port.is_empty() {
        return Err(format!("\"{s}\" names no port; {FORMS}"));
    }
    Ok(Connect::Serial { port: port.to_string(), baud })
}

fn build_galvo(cx: &Cx<'_>, i: usize, g: RawGalvo) -> Result<Galvo, RigError> {
    let k = |f: &str| format!("galvo[{i}].{f}");
    let axis = |name: &str, a: &RawGalvoAxis| -> Result<GalvoAxisSpec, RigError> {
        let k = |f: &str| format!("galvo[{i}].{name}.{f}");
        Ok(GalvoAxisSpec {
            min_code: cx.code(&k("min_code"), a.min_code)?,
            max_code: cx.code(&k("max_code"), a.max_code)?,
            zero_code: cx.code(&k("zero_code"), a.zero_code)?,
            urad_per_code: cx.finite(&k("urad_per_code"), a.urad_per_code)?,
        })
    };
    let (x, y) = (axis("x", &g.x)?, axis("y", &g.y)?);
    let park = match g.park {
        None => [x.zero_code, y.zero_code],
        Some(p) if p.len() == 2 => [cx.code(&k("park[0]"), p[0])?, cx.code(&k("park[1]"), p[1])?],
        Some(p) => {
            return Err(
                cx.err(&k("park"), format!("must be [x, y] (two DAC codes), found {} values", p.len()))
            )
        }
    };
    Ok(Galvo {
        galvo: cx.index(&k("galvo"), g.galvo, MAX_GALVOS, "galvo pairs")?,
        name: g.name,
        dac: cx.choice(&k("dac"), &g.dac, DACS)?,
        x,
        y,
        park,
        settle_us: cx.nonneg(&k("settle_us"), g.settle_us)?,
    })
}

fn build_laser(cx: &Cx<'_>, i: usize, l: RawLaser) -> Result<Laser, RigError> {
    let k = |f: &str| format!("laser[{i}].{f}");
    Ok(Laser {
        channel: cx.index(&k("channel"), l.channel, MAX_LASERS, "laser channels")?,
        name: l.name,
        role: l.role.as_deref().map(|r| cx.choice(&k("role"), r, LASER_ROLES)).transpose()?,
        wavelength_nm: cx.int(&k("wavelength_nm"), l.wavelength_nm, 0, u16::MAX.into())? as u16,
        warmup_ms: cx.nonneg(&k("warmup_ms"), l.warmup_ms)?,
        max_on_s: cx.nonneg(&k("max_on_s"), l.max_on_s)?,
        enable: cx.opt_choice(&k("enable"), l.enable.as_deref(), Polarity::ActiveHigh, POLARITIES)?,
        interlock: cx.choice(&k("interlock"), &l.interlock, INPUTS)?,
    })
}

fn build_stepper(cx: &Cx<'_>, i: usize, s: RawStepper) -> Result<Stepper, RigError> {
    let k = |f: &str| format!("stepper[{i}].{f}");
    let steps_per_unit = match &s.steps_per_unit {
        toml::Value::String(r) => parse_ratio(r).map_err(|m| cx.err(&k("steps_per_unit"), m))?,
        toml::Value::Integer(n) if *n > 0 && *n <= i64::from(u32::MAX) => Ratio { num: *n as u32, den: 1 },
        toml::Value::Integer(_) => {
            return Err(cx.err(&k("steps_per_unit"), "must be a positive 32-bit integer"))
        }
        toml::Value::Float(f) => {
            return Err(cx.err(
                &k("steps_per_unit"),
                format!(
                    "{f} is a float; write an integer or an exact ratio string such as \"3200/360\" \
                     or \"200*16*90/360\""
                ),
            ))
        }
        other => {
            return Err(cx.err(
                &k("steps_per_unit"),
                format!(
                    "expected an integer or a ratio string such as \"200*16*90/360\", found {}",
                    other.type_str()
                ),
            ))
        }
    };
    let limits = match s.limits {
        None => None,
        Some(l) if l.len() == 2 => {
            Some((cx.finite(&k("limits[0]"), l[0])?, cx.finite(&k("limits[1]"), l[1])?))
        }
        Some(l) => {
            let unit = cx.choice(&k("kind"), &s.kind, AXIS_KINDS).map_or("units", unit_name);
            return Err(
                cx.err(&k("limits"), format!("must be [min, max] in {unit}: two numbers, not {}", l.len()))
            );
        }
    };
    let homing = match s.homing {
        None => HomingSpec { mode: HomingMode::None, speed: 0.0, backoff: 0.0, position: 0.0 },
        Some(h) => {
            let mode = cx.choice(&k("homing.mode"), &h.mode, HOMING_MODES)?;
            let speed = match (h.speed, mode) {
                (Some(v), _) => cx.nonneg(&k("homing.speed"), v)?,
                (None, HomingMode::None) => 0.0,
                (None, _) => {
                    return Err(cx.err(
                        &k("homing.speed"),
                        format!(
                            "required when homing.mode = \"{}\": the seek speed in {}/s",
                            h.mode,
                            cx.choice(&k("kind"), &s.kind, AXIS_KINDS).map_or("units", unit_name)
                        ),
                    ))
                }
            };
            HomingSpec {
                mode,
                speed,
                backoff: cx.nonneg(&k("homing.backoff"), h.backoff)?,
                position: cx.finite(&k("homing.position"), h.position)?,
            }
        }
    };
    let unused = Input::Unused;
    Ok(Stepper {
        axis: cx.index(&k("axis"), s.axis, MAX_STEPPERS, "stepper axes")?,
        name: s.name,
        kind: cx.choice(&k("kind"), &s.kind, AXIS_KINDS)?,
        steps_per_unit,
        max_speed: cx.nonneg(&k("max_speed"), s.max_speed)?,
        accel: cx.nonneg(&k("accel"), s.accel)?,
        limits,
        homing,
        invert_dir: s.invert_dir,
        enable: cx.opt_choice(&k("enable"), s.enable.as_deref(), Polarity::ActiveHigh, POLARITIES)?,
        limit_min: cx.opt_choice(&k("limit_min"), s.limit_min.as_deref(), unused, INPUTS)?,
        limit_max: cx.opt_choice(&k("limit_max"), s.limit_max.as_deref(), unused, INPUTS)?,
        index: cx.opt_choice(&k("index"), s.index.as_deref(), unused, INPUTS)?,
    })
}

fn build_filter_wheel(cx: &Cx<'_>, i: usize, w: RawFilterWheel) -> Result<FilterWheel, RigError> {
    let k = |f: &str| format!("filter_wheel[{i}].{f}");
    let max = i64::from(MAX_FILTER_SLOTS);
    let filters = w.filters.unwrap_or_default();
    let slots = match (w.slots, filters.len()) {
        (None, 0) => {
            return Err(cx.err(
                &format!("filter_wheel[{i}]"),
                "give slots = N or filters = [\"name\", …] (one name per slot)",
            ))
        }
        (None, n) => {
            if !(2..=max as usize).contains(&n) {
                return Err(cx.err(&k("filters"), format!("lists {n} filters; a wheel has 2..={max} slots")));
            }
            n as u8
        }
        (Some(s), n) => {
            let s = cx.int(&k("slots"), s, 2, max)? as u8;
            if n != 0 && n != usize::from(s) {
                return Err(cx.err(
                    &k("filters"),
                    format!("lists {n} filters but slots = {s}; give one name per slot (or drop slots)"),
                ));
            }
            s
        }
    };
    for (j, f) in filters.iter().enumerate() {
        if let Some(first) = filters[..j].iter().position(|g| g == f) {
            return Err(cx.err(
                &k(&format!("filters[{j}]")),
                format!(
                    "\"{f}\" is also slot {first}; slot names must be unique so plans can select by name"
                ),
            ));
        }
    }
    Ok(FilterWheel {
        wheel: cx.index(&k("wheel"), w.wheel, MAX_FILTER_WHEELS, "filter wheels")?,
        name: w.name,
        slots,
        filters,
        steps_per_rev: cx.int(&k("steps_per_rev"), w.steps_per_rev, 1, i32::MAX.into())? as u32,
        max_speed: cx.nonneg(&k("max_speed"), w.max_speed)?,
        accel: cx.nonneg(&k("accel"), w.accel)?,
        index: cx.choice(&k("index"), &w.index, INPUTS)?,
        index_offset: cx.int(&k("index_offset"), w.index_offset, i32::MIN.into(), i32::MAX.into())? as i32,
        invert_dir: w.invert_dir,
        enable: cx.opt_choice(&k("enable"), w.enable.as_deref(), Polarity::ActiveHigh, POLARITIES)?,
    })
}

fn build_voice_coil(cx: &Cx<'_>, i: usize, v: RawVoiceCoil) -> Result<VoiceCoil, RigError> {
    let k = |f: &str| format!("voice_coil[{i}].{f}");
    let amp = cx.nonneg(&k("max_amplitude"), v.max_amplitude)?;
    if amp > 1.0 {
        return Err(cx.err(&k("max_amplitude"), "must be at most 1.0 (full scale)"));
    }
    Ok(VoiceCoil {
        channel: cx.index(&k("channel"), v.channel, MAX_VOICE_COILS, "voice-coil channels")?,
        name: v.name,
        sample_rate_hz: cx.int(&k("sample_rate_hz"), v.sample_rate_hz, 0, u32::MAX.into())? as u32,
        max_amplitude: amp,
    })
}

/// A camera's frame source; relative directories are taken from the rig file's directory.
fn build_source(cx: &Cx<'_>, i: usize, s: Option<RawSource>) -> Result<FrameSource, RigError> {
    const EXAMPLE: &str = "e.g. \"img_{frame:06}.png\"";
    let k = |f: &str| format!("camera[{i}].source.{f}");
    let Some(s) = s else { return Ok(FrameSource::Virtual { gamma: 1.0 }) };
    let kinds: Vec<_> = SOURCE_KINDS.iter().map(|s| (*s, *s)).collect();
    let kind = cx.choice(&k("kind"), &s.kind, &kinds)?;
    if kind != "genicam" {
        let keys = [
            ("address", s.address.is_some()),
            ("trigger", s.trigger.is_some()),
            ("activation", s.activation.is_some()),
            ("pixel_format", s.pixel_format.is_some()),
            ("exposure_us", s.exposure_us.is_some()),
            ("buffers", s.buffers.is_some()),
        ];
        if let Some((key, _)) = keys.iter().find(|(_, set)| *set) {
            return Err(cx.err(&k(key), "only for kind = \"genicam\" (a GenICam camera read through Aravis)"));
        }
    }
    if kind == "genicam" {
        for (key, set) in
            [("path", s.path.is_some()), ("pattern", s.pattern.is_some()), ("gamma", s.gamma.is_some())]
        {
            if set {
                return Err(cx.err(&k(key), "not for kind = \"genicam\": the camera streams its frames"));
            }
        }
        let Some(address) = s.address.filter(|a| !a.is_empty()) else {
            let message = "required for kind = \"genicam\": the camera's address (\"192.168.1.20\") or its \
                           Aravis id (`lightrig devices` lists them)";
            return Err(cx.err(&k("address"), message));
        };
        let trigger = s.trigger.unwrap_or_else(|| "software".into());
        if trigger.is_empty() {
            return Err(cx.err(&k("trigger"), "\"software\" or the camera's trigger line, e.g. \"Line0\""));
        }
        if let Some(e) = s.exposure_us.filter(|e| !(e.is_finite() && *e > 0.0)) {
            return Err(cx.err(&k("exposure_us"), format!("{e}: must be a positive time in µs")));
        }
        let buffers = match s.buffers {
            None => 16,
            Some(b) => cx.int(&k("buffers"), b, 2, 1024)? as u32,
        };
        return Ok(FrameSource::Genicam(GenicamSource {
            address,
            trigger,
            activation: s.activation,
            pixel_format: s.pixel_format,
            exposure_us: s.exposure_us,
            buffers,
        }));
    }
    if kind == "virtual" {
        for (key, v) in [("path", &s.path), ("pattern", &s.pattern)] {
            if v.is_some() {
                let message = "only for kind = \"directory\"; a virtual source makes its own frames";
                return Err(cx.err(&k(key), message));
            }
        }
        let gamma = s.gamma.unwrap_or(1.0);
        if !(0.2..=5.0).contains(&gamma) {
            return Err(
                cx.err(&k("gamma"), "must be in 0.2..=5.0 (1 is a linear camera, 2.2 a display gamma)")
            );
        }
        return Ok(FrameSource::Virtual { gamma });
    }
    if s.gamma.is_some() {
        let message = "only for kind = \"virtual\": a real camera's curve is its `response` file";
        return Err(cx.err(&k("gamma"), message));
    }
    let Some(path) = s.path else {
        let message = "required for kind = \"directory\": the directory the frames appear in";
        return Err(cx.err(&k("path"), message));
    };
    let Some(pattern) = s.pattern else {
        let message = format!("required for kind = \"directory\": the file name of frame N, {EXAMPLE}");
        return Err(cx.err(&k("pattern"), message));
    };
    if crate::frames::Pattern::parse(&pattern).is_err() {
        let message = format!(
            "\"{pattern}\" needs exactly one {{frame}} or {{frame:0N}} placeholder (N digits, zero-padded), \
             {EXAMPLE}"
        );
        return Err(cx.err(&k("pattern"), message));
    }
    let base = cx.path.parent().unwrap_or(Path::new(""));
    Ok(FrameSource::Directory { dir: base.join(path), pattern })
}

fn build_camera(cx: &Cx<'_>, i: usize, c: RawCamera) -> Result<Camera, RigError> {
    let k = |f: &str| format!("camera[{i}].{f}");
    let source = build_source(cx, i, c.source)?;
    Ok(Camera {
        camera: cx.index(&k("camera"), c.camera, MAX_CAMERAS, "camera outputs")?,
        name: c.name,
        pulse_us: cx.nonneg(&k("pulse_us"), c.pulse_us)?,
        polarity: cx.opt_choice(&k("polarity"), c.polarity.as_deref(), Polarity::ActiveHigh, POLARITIES)?,
        exposure_input: cx.opt_choice(
            &k("exposure_input"),
            c.exposure_input.as_deref(),
            Input::Unused,
            INPUTS,
        )?,
        min_interval_us: cx.nonneg(&k("min_interval_us"), c.min_interval_us)?,
        source,
        response: c.response.map(|r| cx.path.parent().unwrap_or(Path::new("")).join(r)),
    })
}

/// A TOML syntax error.
fn syntax_error(e: &toml::de::Error, text: &str, path: &Path) -> RigError {
    let line = e.span().map(|s| Lines::new(text).at(s.start));
    let mut message = e.message().to_string();
    if message == "duplicate key" {
        if let Some(s) = e.span() {
            message = format!("duplicate key \"{}\"; each key may appear once per table", &text[s]);
        }
    }
    RigError {
        path: path.to_path_buf(),
        line,
        key: String::new(),
        message: format!("invalid TOML: {message}"),
    }
}

/// A serde error (unknown key, missing key, wrong type) with its key path and line.
fn serde_error(e: &toml::de::Error, nodes: &[Node], lines: &Lines, path: &Path) -> RigError {
    let msg = e.message();
    // The root table's span is empty: an error there (a missing top-level key) has no line.
    let at = e.span().filter(|s| !s.is_empty()).and_then(|s| locate(nodes, &s).map(|n| (n, s)));
    let mut key = at.as_ref().map_or(String::new(), |(n, _)| n.path.clone());
    let mut line = at.map(|(n, s)| if n.key == s { n.line } else { lines.at(s.start) });
    let message = if let Some(rest) = msg.strip_prefix("unknown field ") {
        let names = backquoted(rest);
        let (word, valid) = names.split_first().map_or(("", &[][..]), |(w, v)| (*w, v));
        let list = valid.join(", ");
        match suggest(word, valid.iter().copied()) {
            Some(s) => format!("unknown key; did you mean \"{s}\"? Valid keys here: {list}"),
            None if valid.is_empty() => "unknown key; this table takes no keys".to_string(),
            None => format!("unknown key; valid keys here: {list}"),
        }
    } else if let Some(rest) = msg.strip_prefix("missing field ") {
        let field = backquoted(rest).first().copied().unwrap_or(rest);
        if key.is_empty() {
            line = None;
        }
        let hint = key_hint(&key, field);
        key = join(&key, field);
        match hint {
            Some(h) => format!("required key is missing ({h})"),
            None => "required key is missing".to_string(),
        }
    } else if let Some(rest) = msg.strip_prefix("invalid type: ") {
        match rest.split_once(", expected ") {
            Some((found, expected)) => format!("expected {}, found {found}", type_words(expected)),
            None => msg.to_string(),
        }
    } else {
        msg.to_string()
    };
    RigError { path: path.to_path_buf(), line, key, message }
}

impl RigFile {
    /// Reads and parses a rig file.
    pub fn load(path: &Path) -> Result<RigFile, RigError> {
        let text = std::fs::read_to_string(path).map_err(|e| RigError {
            path: path.to_path_buf(),
            line: None,
            key: String::new(),
            message: format!("cannot read the rig file: {e}"),
        })?;
        Self::parse(&text, path)
    }

    /// Parses rig-file text; `path` names it in errors and anchors relative frame directories.
    /// Checks everything that does not depend on the device.
    pub fn parse(text: &str, path: &Path) -> Result<RigFile, RigError> {
        let doc = DeTable::parse(text).map_err(|e| syntax_error(&e, text, path))?;
        let line_index = Lines::new(text);
        let mut nodes = Vec::new();
        index_table(doc.get_ref(), "", &line_index, &mut nodes);
        let raw: RawRig = toml::from_str(text).map_err(|e| serde_error(&e, &nodes, &line_index, path))?;
        let lines: BTreeMap<String, usize> = nodes.iter().map(|n| (n.path.clone(), n.line)).collect();
        let cx = Cx { path, lines: &lines };

        let method = cx.choice("rig.method", &raw.rig.method, METHODS)?;
        let connect = match raw.device.and_then(|d| d.connect) {
            None => Connect::Virtual,
            Some(c) => parse_connect(&c).map_err(|m| cx.err("device.connect", m))?,
        };
        let safety = match raw.safety {
            None => None,
            Some(s) => Some(Safety {
                heartbeat_timeout_ms: cx.nonneg("safety.heartbeat_timeout_ms", s.heartbeat_timeout_ms)?,
            }),
        };
        let galvos = raw.galvo.into_iter().enumerate().map(|(i, g)| build_galvo(&cx, i, g));
        let galvos = galvos.collect::<Result<Vec<_>, _>>()?;
        let lasers = raw.laser.into_iter().enumerate().map(|(i, l)| build_laser(&cx, i, l));
        let lasers = lasers.collect::<Result<Vec<_>, _>>()?;
        let steppers = raw.stepper.into_iter().enumerate().map(|(i, s)| build_stepper(&cx, i, s));
        let steppers = steppers.collect::<Result<Vec<_>, _>>()?;
        let wheels = raw.filter_wheel.into_iter().enumerate().map(|(i, w)| build_filter_wheel(&cx, i, w));
        let filter_wheels = wheels.collect::<Result<Vec<_>, _>>()?;
        let coils = raw.voice_coil.into_iter().enumerate().map(|(i, v)| build_voice_coil(&cx, i, v));
        let voice_coils = coils.collect::<Result<Vec<_>, _>>()?;
        let cameras = raw.camera.into_iter().enumerate().map(|(i, c)| build_camera(&cx, i, c));
        let cameras = cameras.collect::<Result<Vec<_>, _>>()?;

        let g: Vec<_> = galvos.iter().map(|g| (g.galvo, g.name.as_deref())).collect();
        no_duplicates(&cx, "galvo", "galvo", &g)?;
        let l: Vec<_> = lasers.iter().map(|l| (l.channel, l.name.as_deref())).collect();
        no_duplicates(&cx, "laser", "channel", &l)?;
        laser_roles(&cx, method, &lasers)?;
        let s: Vec<_> = steppers.iter().map(|s| (s.axis, s.name.as_deref())).collect();
        no_duplicates(&cx, "stepper", "axis", &s)?;
        let w: Vec<_> = filter_wheels.iter().map(|w| (w.wheel, w.name.as_deref())).collect();
        no_duplicates(&cx, "filter_wheel", "wheel", &w)?;
        let v: Vec<_> = voice_coils.iter().map(|v| (v.channel, v.name.as_deref())).collect();
        no_duplicates(&cx, "voice_coil", "channel", &v)?;
        let c: Vec<_> = cameras.iter().map(|c| (c.camera, c.name.as_deref())).collect();
        no_duplicates(&cx, "camera", "camera", &c)?;

        Ok(RigFile {
            path: path.to_path_buf(),
            name: raw.rig.name,
            description: raw.rig.description,
            method,
            connect,
            galvos,
            lasers,
            steppers,
            filter_wheels,
            voice_coils,
            cameras,
            safety,
            plan: raw.plan,
            lines,
        })
    }

    /// Line of a key path (`stepper[0].limits`, `plan.disco.views`), or of the nearest
    /// enclosing key present in the file.
    pub fn line_of(&self, key: &str) -> Option<usize> {
        line_of(&self.lines, key)
    }

    /// `key` (a dotted path) is no key of its table: the error, with the closest of `valid`
    /// as a suggestion, as serde's unknown keys elsewhere in the file are reported.
    pub fn unknown_key(&self, key: &str, valid: &[&str]) -> RigError {
        let word = key.rsplit('.').next().unwrap_or(key);
        let list = valid.join(", ");
        let message = match suggest(word, valid.iter().copied()) {
            Some(s) => format!("unknown key; did you mean \"{s}\"? Valid keys here: {list}"),
            None => format!("unknown key; valid keys here: {list}"),
        };
        self.error(key, message)
    }

    /// An error about `key` of this file (for the planners checking `[plan]`).
    pub fn error(&self, key: &str, message: impl Into<String>) -> RigError {
        RigError {
            path: self.path.clone(),
            line: self.line_of(key),
            key: key.to_string(),
            message: message.into(),
        }
    }

    /// The stepper with device axis `axis`.
    pub fn stepper(&self, axis: u8) -> Option<&Stepper> {
        self.steppers.iter().find(|s| s.axis == axis)
    }

    /// The stepper called `name`.
    pub fn stepper_named(&self, name: &str) -> Option<&Stepper> {
        self.steppers.iter().find(|s| s.name.as_deref() == Some(name))
    }

    /// The laser whose `role` is `role`.
    pub fn laser_with_role(&self, role: LaserRole) -> Option<&Laser> {
        self.lasers.iter().find(|l| l.role == Some(role))
    }

    /// The laser on device channel `channel`.
    pub fn laser(&self, channel: u8) -> Option<&Laser> {
        self.lasers.iter().find(|l| l.channel == channel)
    }

    /// The camera on device output `camera`.
    pub fn camera(&self, camera: u8) -> Option<&Camera> {
        self.cameras.iter().find(|c| c.camera == camera)
    }

    /// Where camera `camera`'s frames come from.
    pub fn camera_source(&self, camera: u8) -> Option<&FrameSource> {
        self.camera(camera).map(|c| &c.source)
    }

    /// Steps of stepper `axis` at `value` units (mm or degrees), checked against its soft
    /// limits.
    pub fn stepper_steps(&self, axis: u8, value: f64) -> Result<i32, RigError> {
        let Some(i) = self.steppers.iter().position(|s| s.axis == axis) else {
            let axes: Vec<String> = self.steppers.iter().map(|s| s.axis.to_string()).collect();
            return Err(self.error(
                "stepper",
                format!("no [[stepper]] has axis = {axis}; configured axes: [{}]", axes.join(", ")),
            ));
        };
        let s = &self.steppers[i];
        let u = s.unit();
        if let Some((lo, hi)) = s.limits {
            if !(lo..=hi).contains(&value) {
                return Err(self.error(
                    &format!("stepper[{i}].limits"),
                    format!("{value} {u} is outside the limits {lo}..={hi} {u}"),
                ));
            }
        }
        s.steps(value).and_then(|v| i32::try_from(v).ok()).ok_or_else(|| {
            self.error(
                &format!("stepper[{i}].steps_per_unit"),
                format!("{value} {u} does not fit in 32-bit steps"),
            )
        })
    }

    /// Slot of filter wheel `wheel` named `name` (from its `filters` list).
    pub fn filter_slot(&self, wheel: u8, name: &str) -> Result<u8, RigError> {
        let Some(i) = self.filter_wheels.iter().position(|w| w.wheel == wheel) else {
            return Err(self.error("filter_wheel", format!("no [[filter_wheel]] has wheel = {wheel}")));
        };
        let w = &self.filter_wheels[i];
        if let Some(slot) = w.filters.iter().position(|f| f == name) {
            return Ok(slot as u8);
        }
        let key = format!("filter_wheel[{i}].filters");
        if w.filters.is_empty() {
            return Err(
                self.error(&key, format!("no slot is named \"{name}\": the wheel's slots have no names"))
            );
        }
        let list = quoted_list(w.filters.iter().map(String::as_str));
        let hint = suggest(name, w.filters.iter().map(String::as_str))
            .map_or(String::new(), |s| format!("did you mean \"{s}\"? "));
        Err(self.error(&key, format!("no slot is named \"{name}\"; {hint}slots: {list}")))
    }

    /// The device configuration, one item per peripheral (safety first, then galvos, lasers,
    /// steppers, filter wheels, voice coils, cameras, each in file order), converted for
    /// `info.tick_hz` and validated against `info` with [`ConfigItem::validate`]. The first
    /// refusal is reported at the rig-file key and line it comes from, in the file's units.
    pub fn config_items(&self, info: &DeviceInfo) -> Result<Vec<ConfigItem>, RigError> {
        let hz = info.tick_hz;
        let mut items = Vec::new();
        let mut push = |item: ConfigItem, at: usize| -> Result<(), RigError> {
            item.validate(info).map_err(|e| self.device_error(&e, at, info))?;
            items.push(item);
            Ok(())
        };
        if let Some(s) = &self.safety {
            let t = self.time("safety.heartbeat_timeout_ms", s.heartbeat_timeout_ms, MS, hz)?;
            push(ConfigItem::Safety(SafetyConfig { heartbeat_timeout_ticks: t }), 0)?;
        }
        for (i, g) in self.galvos.iter().enumerate() {
            let axis = |name: &str, a: &GalvoAxisSpec| -> Result<GalvoAxis, RigError> {
                let key = format!("galvo[{i}].{name}.urad_per_code");
                let nrad = scaled(a.urad_per_code, 1_000, 1).and_then(|v| i32::try_from(v).ok());
                let nrad = nrad.ok_or_else(|| {
                    self.error(
                        &key,
                        format!("must lie within ±{} µrad", fmt_micro(i128::from(i32::MAX) * 1_000)),
                    )
                })?;
                Ok(GalvoAxis {
                    min_code: a.min_code,
                    max_code: a.max_code,
                    zero_code: a.zero_code,
                    nanorad_per_code: nrad,
                })
            };
            let item = GalvoConfig {
                galvo: g.galvo,
                dac: g.dac,
                x: axis("x", &g.x)?,
                y: axis("y", &g.y)?,
                park: Xy { x: g.park[0], y: g.park[1] },
                settle_ticks: self.time(&format!("galvo[{i}].settle_us"), g.settle_us, US, hz)?,
            };
            push(ConfigItem::Galvo(item), i)?;
        }
        for (i, l) in self.lasers.iter().enumerate() {
            let item = LaserConfig {
                channel: l.channel,
                wavelength_nm: l.wavelength_nm,
                warmup_ticks: self.time(&format!("laser[{i}].warmup_ms"), l.warmup_ms, MS, hz)?,
                max_on_ticks: self.time(&format!("laser[{i}].max_on_s"), l.max_on_s, S, hz)?,
                enable: l.enable,
                interlock: l.interlock,
            };
            push(ConfigItem::Laser(item), i)?;
        }
        for (i, s) in self.steppers.iter().enumerate() {
            let k = |f: &str| format!("stepper[{i}].{f}");
            let r = s.steps_per_unit;
            let rate = |v: f64| saturate_u32(r.steps_from_micro(micro(v).unwrap_or(i64::MAX)));
            let position = |key: &str, v: f64| -> Result<i32, RigError> {
                s.steps(v).and_then(|v| i32::try_from(v).ok()).ok_or_else(|| {
                    let max = r.micro_from_steps(i32::MAX.into()).unwrap_or(i64::MAX);
                    let u = s.unit();
                    self.error(
                        &k(key),
                        format!("must lie within ±{} {u} (±2147483647 steps)", fmt_micro(max.into())),
                    )
                })
            };
            let limits = match s.limits {
                None => None,
                Some((lo, hi)) => {
                    Some(StepRange { min: position("limits[0]", lo)?, max: position("limits[1]", hi)? })
                }
            };
            let backoff = u32::try_from(position("homing.backoff", s.homing.backoff)?).unwrap_or(0);
            let item = StepperConfig {
                axis: s.axis,
                kind: s.kind,
                steps_per_unit: r,
                max_speed: rate(s.max_speed),
                accel: rate(s.accel),
                limits,
                homing: Homing {
                    mode: s.homing.mode,
                    speed: rate(s.homing.speed),
                    backoff,
                    position: position("homing.position", s.homing.position)?,
                },
                invert_dir: s.invert_dir,
                enable: s.enable,
                limit_min: s.limit_min,
                limit_max: s.limit_max,
                index: s.index,
            };
            push(ConfigItem::Stepper(item), i)?;
        }
        for (i, w) in self.filter_wheels.iter().enumerate() {
            let rate = |v: f64| {
                saturate_u32(scaled(v, w.steps_per_rev.into(), 1).and_then(|v| i64::try_from(v).ok()))
            };
            let item = FilterWheelConfig {
                wheel: w.wheel,
                slots: w.slots,
                steps_per_rev: w.steps_per_rev,
                max_speed: rate(w.max_speed),
                accel: rate(w.accel),
                index: w.index,
                index_offset: w.index_offset,
                invert_dir: w.invert_dir,
                enable: w.enable,
            };
            push(ConfigItem::FilterWheel(item), i)?;
        }
        for (i, v) in self.voice_coils.iter().enumerate() {
            let amp =
                scaled(v.max_amplitude, u16::MAX.into(), 1).and_then(|a| u16::try_from(a).ok()).unwrap_or(0);
            let item =
                VoiceCoilConfig { channel: v.channel, sample_rate_hz: v.sample_rate_hz, max_amplitude: amp };
            push(ConfigItem::VoiceCoil(item), i)?;
        }
        for (i, c) in self.cameras.iter().enumerate() {
            let item = CameraConfig {
                camera: c.camera,
                pulse_ticks: self.time(&format!("camera[{i}].pulse_us"), c.pulse_us, US, hz)?,
                polarity: c.polarity,
                exposure_input: c.exposure_input,
                min_interval_ticks: self.time(
                    &format!("camera[{i}].min_interval_us"),
                    c.min_interval_us,
                    US,
                    hz,
                )?,
            };
            push(ConfigItem::Camera(item), i)?;
        }
        Ok(items)
    }

    /// Ticks for a duration, or an error saying how long the device can count.
    fn time(&self, key: &str, value: f64, (unit, unit_hz): TimeUnit, tick_hz: u32) -> Result<u32, RigError> {
        ticks(value, unit_hz, tick_hz).ok_or_else(|| {
            let max = u32::MAX;
            let max_micro = i128::from(max) * i128::from(unit_hz) * 1_000_000 / i128::from(tick_hz.max(1));
            let message = format!(
                "{value} {unit} is too long: at {tick_hz} Hz the device counts at most {max} ticks \
                 ({} {unit})",
                fmt_micro(max_micro)
            );
            self.error(key, message)
        })
    }

    /// A device-side refusal of the item from entry `at`, at its rig-file key, in file units.
    fn device_error(&self, e: &ConfigError, at: usize, info: &DeviceInfo) -> RigError {
        use ConfigField as F;
        use InvalidReason as R;
        let generic = |r: &InvalidReason| -> String {
            match *r {
                R::Zero => "must not be zero".into(),
                R::TooSmall { min } => format!("must be at least {min}"),
                R::TooLarge { max } => format!("must be at most {max}"),
                R::EmptyRange => "min must be below max".into(),
                R::OutsideRange { min, max } => format!("must lie within {min}..={max}"),
                R::Required => "is required here".into(),
                R::NeedsInput => "needs an input that is configured \"unused\"".into(),
                R::NoSuchPeripheral { count } => format!("the device has only {count} of these"),
            }
        };
        let (key, message): (String, String) = match e.field {
            F::GalvoIndex
            | F::GalvoXMinCode
            | F::GalvoXMaxCode
            | F::GalvoXZeroCode
            | F::GalvoXNanoradPerCode
            | F::GalvoYMinCode
            | F::GalvoYMaxCode
            | F::GalvoYZeroCode
            | F::GalvoYNanoradPerCode
            | F::GalvoParkX
            | F::GalvoParkY => {
                let g = &self.galvos[at];
                let p = format!("galvo[{at}]");
                let (axis, a) = match e.field {
                    F::GalvoXMinCode
                    | F::GalvoXMaxCode
                    | F::GalvoXZeroCode
                    | F::GalvoXNanoradPerCode
                    | F::GalvoParkX => ("x", &g.x),
                    _ => ("y", &g.y),
                };
                match (e.field, e.reason) {
                    (F::GalvoIndex, R::NoSuchPeripheral { count }) => {
                        (format!("{p}.galvo"), no_such(count, "galvo pair", "galvo pairs", "galvo", "galvos"))
                    }
                    (F::GalvoXMaxCode | F::GalvoYMaxCode, R::TooLarge { max }) => (
                        format!("{p}.{axis}.max_code"),
                        format!(
                            "must be at most {max}, the largest code of dac = \"{}\"",
                            name_of(DACS, g.dac)
                        ),
                    ),
                    (F::GalvoXMinCode | F::GalvoYMinCode, R::EmptyRange) => (
                        format!("{p}.{axis}.min_code"),
                        format!("must be below max_code ({}): the range would be empty", a.max_code),
                    ),
                    (F::GalvoXZeroCode | F::GalvoYZeroCode, R::OutsideRange { min, max }) => (
                        format!("{p}.{axis}.zero_code"),
                        format!("must lie within min_code..=max_code ({min}..={max})"),
                    ),
                    (F::GalvoXNanoradPerCode | F::GalvoYNanoradPerCode, R::Zero) => (
                        format!("{p}.{axis}.urad_per_code"),
                        if a.urad_per_code == 0.0 {
                            "must not be zero".into()
                        } else {
                            format!(
                                "{} µrad rounds to 0 nrad per code; its magnitude must be at least 0.0005",
                                a.urad_per_code
                            )
                        },
                    ),
                    (F::GalvoParkX | F::GalvoParkY, R::OutsideRange { min, max }) => {
                        let (idx, code) = if axis == "x" { (0, g.park[0]) } else { (1, g.park[1]) };
                        (
                            format!("{p}.park[{idx}]"),
                            format!(
                                "{axis} = {code} must lie within {axis}.min_code..={axis}.max_code \
                                 ({min}..={max})"
                            ),
                        )
                    }
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("galvo.")), generic(&r)),
                }
            }
            F::LaserChannel | F::LaserWavelength | F::LaserMaxOnTicks | F::LaserWarmupTicks => {
                let l = &self.lasers[at];
                let p = format!("laser[{at}]");
                match (e.field, e.reason) {
                    (F::LaserChannel, R::NoSuchPeripheral { count }) => {
                        (format!("{p}.channel"), no_such(count, "laser", "lasers", "channel", "channels"))
                    }
                    (F::LaserWavelength, _) => {
                        let (lo, hi) = WAVELENGTH_RANGE;
                        (format!("{p}.wavelength_nm"), format!("must lie within {lo}..={hi} nm"))
                    }
                    (F::LaserMaxOnTicks, R::Zero) => (
                        format!("{p}.max_on_s"),
                        if l.max_on_s == 0.0 {
                            "must not be zero: it is the longest the laser may stay on".into()
                        } else {
                            format!(
                                "{} s rounds to 0 ticks at {} Hz; must not be zero",
                                l.max_on_s, info.tick_hz
                            )
                        },
                    ),
                    (F::LaserWarmupTicks, R::TooLarge { .. }) => (
                        format!("{p}.warmup_ms"),
                        format!(
                            "{} ms is longer than max_on_s ({} s): the laser would fault before it is ready",
                            l.warmup_ms, l.max_on_s
                        ),
                    ),
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("laser.")), generic(&r)),
                }
            }
            F::StepperAxis
            | F::StepperStepsPerUnit
            | F::StepperMaxSpeed
            | F::StepperAccel
            | F::StepperLimits
            | F::StepperHomingMode
            | F::StepperHomingSpeed
            | F::StepperHomingPosition => {
                let s = &self.steppers[at];
                let p = format!("stepper[{at}]");
                let u = s.unit();
                let r = s.steps_per_unit;
                let in_units = |steps: i64| fmt_micro(r.micro_from_steps(steps).unwrap_or(0).into());
                let at_ratio = format!("at {} steps/{u}", fmt_ratio(r));
                match (e.field, e.reason) {
                    (F::StepperAxis, R::NoSuchPeripheral { count }) => {
                        (format!("{p}.axis"), no_such(count, "stepper axis", "stepper axes", "axis", "axes"))
                    }
                    (F::StepperMaxSpeed, R::TooLarge { max }) => (
                        format!("{p}.max_speed"),
                        format!("must be at most {} {u}/s ({max} steps/s {at_ratio})", in_units(max)),
                    ),
                    (F::StepperMaxSpeed, R::TooSmall { min }) => (
                        format!("{p}.max_speed"),
                        format!("must be at least {} {u}/s ({min} step/s {at_ratio})", in_units(min)),
                    ),
                    (F::StepperAccel, R::Zero) => (
                        format!("{p}.accel"),
                        format!("must be at least {} {u}/s² (1 step/s² {at_ratio})", in_units(1)),
                    ),
                    (F::StepperLimits, R::Required) => (
                        format!("{p}.limits"),
                        format!("required for a linear axis: limits = [min, max] in {u}"),
                    ),
                    (F::StepperLimits, R::EmptyRange) => {
                        let (lo, hi) = s.limits.unwrap_or((0.0, 0.0));
                        let message = if lo < hi {
                            format!("{lo} and {hi} {u} are the same step {at_ratio}; min must be below max")
                        } else {
                            format!("min ({lo} {u}) must be below max ({hi} {u})")
                        };
                        (format!("{p}.limits"), message)
                    }
                    (F::StepperHomingMode, R::NeedsInput) => {
                        let (mode, input) = match s.homing.mode {
                            HomingMode::ToMinLimit => ("min", "limit_min"),
                            HomingMode::ToMaxLimit => ("max", "limit_max"),
                            _ => ("index", "index"),
                        };
                        (
                            format!("{p}.homing.mode"),
                            format!(
                                "mode \"{mode}\" seeks the {input} input, but {input} is \"unused\"; wire it \
                                 ({input} = \"high\" or \"low\") or choose another mode"
                            ),
                        )
                    }
                    (F::StepperHomingSpeed, R::TooLarge { .. }) => (
                        format!("{p}.homing.speed"),
                        format!("must be at most max_speed ({} {u}/s)", s.max_speed),
                    ),
                    (F::StepperHomingSpeed, R::TooSmall { min }) => (
                        format!("{p}.homing.speed"),
                        format!("must be at least {} {u}/s ({min} step/s {at_ratio})", in_units(min)),
                    ),
                    (F::StepperHomingPosition, R::OutsideRange { .. }) => {
                        let (lo, hi) = s.limits.unwrap_or((0.0, 0.0));
                        (
                            format!("{p}.homing.position"),
                            format!("must lie within the limits {lo}..={hi} {u}"),
                        )
                    }
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("stepper.")), generic(&r)),
                }
            }
            F::FilterWheelIndex
            | F::FilterWheelSlots
            | F::FilterWheelStepsPerRev
            | F::FilterWheelMaxSpeed
            | F::FilterWheelAccel
            | F::FilterWheelIndexSensor
            | F::FilterWheelIndexOffset => {
                let w = &self.filter_wheels[at];
                let p = format!("filter_wheel[{at}]");
                let in_revs =
                    |steps: i64| fmt_micro(i128::from(steps) * 1_000_000 / i128::from(w.steps_per_rev));
                let at_ratio = format!("at {} steps/rev", w.steps_per_rev);
                match (e.field, e.reason) {
                    (F::FilterWheelIndex, R::NoSuchPeripheral { count }) => (
                        format!("{p}.wheel"),
                        no_such(count, "filter wheel", "filter wheels", "wheel", "wheels"),
                    ),
                    (F::FilterWheelStepsPerRev, R::TooSmall { min }) => {
                        (format!("{p}.steps_per_rev"), format!("must be at least {min}, one step per slot"))
                    }
                    (F::FilterWheelMaxSpeed, R::TooLarge { max }) => (
                        format!("{p}.max_speed"),
                        format!("must be at most {} rev/s ({max} steps/s {at_ratio})", in_revs(max)),
                    ),
                    (F::FilterWheelMaxSpeed, R::TooSmall { min }) => (
                        format!("{p}.max_speed"),
                        format!("must be at least {} rev/s ({min} step/s {at_ratio})", in_revs(min)),
                    ),
                    (F::FilterWheelAccel, R::Zero) => (
                        format!("{p}.accel"),
                        format!("must be at least {} rev/s² (1 step/s² {at_ratio})", in_revs(1)),
                    ),
                    (F::FilterWheelIndexSensor, R::Required) => (
                        format!("{p}.index"),
                        "must be wired (\"high\" or \"low\"): the wheel homes on its index sensor".into(),
                    ),
                    (F::FilterWheelIndexOffset, R::TooSmall { min } | R::TooLarge { max: min }) => (
                        format!("{p}.index_offset"),
                        format!("must lie within ±{} steps (less than one revolution)", min.abs()),
                    ),
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("filter_wheel.")), generic(&r)),
                }
            }
            F::VoiceCoilChannel | F::VoiceCoilSampleRate | F::VoiceCoilMaxAmplitude => {
                let v = &self.voice_coils[at];
                let p = format!("voice_coil[{at}]");
                match (e.field, e.reason) {
                    (F::VoiceCoilChannel, R::NoSuchPeripheral { count }) => (
                        format!("{p}.channel"),
                        no_such(count, "voice coil", "voice coils", "channel", "channels"),
                    ),
                    (F::VoiceCoilSampleRate, _) => {
                        let (lo, hi) = SAMPLE_RATE_RANGE;
                        (format!("{p}.sample_rate_hz"), format!("must lie within {lo}..={hi} Hz"))
                    }
                    (F::VoiceCoilMaxAmplitude, R::Zero) => (
                        format!("{p}.max_amplitude"),
                        if v.max_amplitude == 0.0 {
                            "must not be zero: the coil could make no sound".into()
                        } else {
                            format!("{} rounds to 0 of 65535; must be at least 1/65535", v.max_amplitude)
                        },
                    ),
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("voice_coil.")), generic(&r)),
                }
            }
            F::CameraIndex | F::CameraPulseTicks => {
                let c = &self.cameras[at];
                let p = format!("camera[{at}]");
                match (e.field, e.reason) {
                    (F::CameraIndex, R::NoSuchPeripheral { count }) => (
                        format!("{p}.camera"),
                        no_such(count, "camera output", "camera outputs", "camera", "cameras"),
                    ),
                    (F::CameraPulseTicks, R::Zero) => (
                        format!("{p}.pulse_us"),
                        if c.pulse_us == 0.0 {
                            "must not be zero".into()
                        } else {
                            format!(
                                "{} µs rounds to 0 ticks at {} Hz; must not be zero",
                                c.pulse_us, info.tick_hz
                            )
                        },
                    ),
                    (f, r) => (format!("{p}.{}", f.name().trim_start_matches("camera.")), generic(&r)),
                }
            }
            F::SafetyHeartbeatTimeout => {
                let (lo, hi) = HEARTBEAT_RANGE_MS;
                ("safety.heartbeat_timeout_ms".into(), format!("must lie within {lo}..={hi} ms"))
            }
        };
        self.error(&key, message)
    }
}

fn saturate_u32(v: Option<i64>) -> u32 {
    match v {
        Some(v) if v < 0 => 0,
        Some(v) => u32::try_from(v).unwrap_or(u32::MAX),
        None => u32::MAX,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimals_are_exact() {
        assert_eq!(exact(0.2), Some((2, 10)));
        assert_eq!(exact(-12.5), Some((-125, 10)));
        assert_eq!(exact(1e-7), Some((1, 10_000_000)));
        assert_eq!(exact(f64::NAN), None);
        assert_eq!(exact(1e300), None);
        assert_eq!(ticks_from_ms(0.2, 1_000_000), Some(200));
        assert_eq!(ticks_from_us(0.5, 1_000_000), Some(1), "ties away from zero");
        assert_eq!(ticks_from_us(0.0005, 1_000_000_000), Some(1));
        assert_eq!(ticks_from_s(4294.967295, 1_000_000), Some(u32::MAX));
        assert_eq!(ticks_from_s(4294.9672955, 1_000_000), None);
        assert_eq!(ticks_from_us(-1.0, 1_000_000), None);
        assert_eq!(micro(0.1234565), Some(123_457));
    }

    #[test]
    fn ratios_reduce() {
        assert_eq!(parse_ratio("80"), Ok(Ratio { num: 80, den: 1 }));
        assert_eq!(parse_ratio("3200/360"), Ok(Ratio { num: 80, den: 9 }));
        assert_eq!(parse_ratio(" 200 * 16 * 90 / 360 "), Ok(Ratio { num: 800, den: 1 }));
        assert_eq!(parse_ratio("1000/3*2"), Ok(Ratio { num: 500, den: 3 }));
        assert!(parse_ratio("1.8").is_err());
        assert!(parse_ratio("80/0").unwrap_err().contains("zero factor"));
        assert!(parse_ratio("1/2/3").is_err());
        assert!(parse_ratio("").is_err());
        assert!(parse_ratio("4294967296").unwrap_err().contains("32 bits"));
    }

    #[test]
    fn frame_patterns() {
        let s = FrameSource::Directory { dir: "frames".into(), pattern: "img_{frame:06}.png".into() };
        assert_eq!(s.frame_path(42), Some(PathBuf::from("frames/img_000042.png")));
        let s = FrameSource::Directory { dir: "f".into(), pattern: "{frame}.exr".into() };
        assert_eq!(s.frame_path(7), Some(PathBuf::from("f/7.exr")));
        assert!(crate::frames::Pattern::parse("img.png").is_err());
        assert!(crate::frames::Pattern::parse("{frame}{frame}.png").is_err());
        assert!(crate::frames::Pattern::parse("{frame:6}.png").is_err());
    }

    #[test]
    fn suggestions() {
        let keys = ["max_speed", "accel", "limits", "kind"];
        assert_eq!(suggest("max_sped", keys), Some("max_speed"));
        assert_eq!(suggest("max_speed_mm_s", keys), Some("max_speed"));
        assert_eq!(suggest("limit", keys), Some("limits"));
        assert_eq!(suggest("colour", keys), None);
    }
}
