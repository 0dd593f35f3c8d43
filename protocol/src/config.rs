//! Rig wiring and limits, sent one peripheral at a time with `Command::Configure`.
//!
//! Every quantity is an integer in device units: DAC codes, steps, ticks (at the device's
//! `tick_hz`), Hz. Host-side units (degrees, millimetres) are converted with each axis'
//! exact rational [`Ratio`] before anything reaches the wire.
//!
//! [`ConfigItem::validate`] is the single definition of what is acceptable. The host runs it
//! before sending (to point at the rig file's line) and the firmware runs it again on receipt;
//! a refusal names the field, the peripheral index and the reason.

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::session::DeviceInfo;
use crate::MAX_FILTER_SLOTS;

/// Electrical level that means "active".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Polarity {
    /// High level (or rising edge) is active.
    ActiveHigh,
    /// Low level (or falling edge) is active.
    ActiveLow,
}

/// A digital input that may be wired or not.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Input {
    /// Not wired; the device ignores the pin.
    Unused,
    /// Wired, with this active level.
    Wired(Polarity),
}

/// Which DAC drives a galvo pair; fixes the frame format and resolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum DacKind {
    /// TI DAC8563, 16-bit dual, over SPI.
    Dac8563,
    /// ADI AD5689, 16-bit dual, over SPI.
    Ad5689,
    /// The microcontroller's own DAC (12-bit).
    McuDac,
    /// XY2-100 digital galvo interface (16-bit, 100 kHz frames).
    Xy2_100,
}

impl DacKind {
    /// Largest code the converter accepts.
    pub const fn max_code(self) -> u16 {
        match self {
            DacKind::McuDac => 4095,
            _ => u16::MAX,
        }
    }
}

/// A galvo position, in DAC codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Xy {
    /// X axis code.
    pub x: u16,
    /// Y axis code.
    pub y: u16,
}

/// Range and calibration of one galvo axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct GalvoAxis {
    /// Lowest code the mirror may be driven to.
    pub min_code: u16,
    /// Highest code the mirror may be driven to.
    pub max_code: u16,
    /// Code at which the optical deflection is zero.
    pub zero_code: u16,
    /// Optical deflection per code, in nanoradians; negative if the axis is mirrored.
    pub nanorad_per_code: i32,
}

/// A galvo pair (`Configure(Galvo)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct GalvoConfig {
    /// Which pair, `0..capabilities.galvos`.
    pub galvo: u8,
    /// Converter driving the pair.
    pub dac: DacKind,
    /// X axis.
    pub x: GalvoAxis,
    /// Y axis.
    pub y: GalvoAxis,
    /// Where the mirrors go when parked (safe state); must lie inside both ranges.
    pub park: Xy,
    /// Ticks to wait after a jump before the spot counts as settled.
    pub settle_ticks: u32,
}

/// A laser channel (`Configure(Laser)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct LaserConfig {
    /// Which channel, `0..capabilities.lasers`.
    pub channel: u8,
    /// Nominal wavelength, for logs and the host's bookkeeping.
    pub wavelength_nm: u16,
    /// Ticks after enabling before the output counts as stable (`LaserReady`).
    pub warmup_ticks: u32,
    /// Longest continuous on-time; exceeding it is a fault. Never zero.
    pub max_on_ticks: u32,
    /// Level of the shutter / TTL enable output that lets light out.
    pub enable: Polarity,
    /// Hardware interlock input; while it is inactive the laser cannot be enabled.
    pub interlock: Input,
}

/// A rational number `num / den`, used for exact unit conversion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Ratio {
    /// Numerator.
    pub num: u32,
    /// Denominator, never zero.
    pub den: u32,
}

/// Divides rounding to the nearest integer, ties away from zero.
fn div_round(num: i128, den: i128) -> Option<i64> {
    if den == 0 {
        return None;
    }
    let (num, den) = if den < 0 { (-num, -den) } else { (num, den) };
    let half = den / 2;
    let q = if num >= 0 { (num + half) / den } else { (num - half) / den };
    i64::try_from(q).ok()
}

impl Ratio {
    /// Steps for `micro` millionths of a host unit (µm on a linear axis, µ° on a turntable),
    /// rounded to the nearest step (ties away from zero). Exact integer arithmetic, so a
    /// position planned in units lands on the same step every time. `None` if `den` is zero
    /// or the result does not fit.
    pub fn steps_from_micro(&self, micro: i64) -> Option<i64> {
        div_round(i128::from(micro) * i128::from(self.num), i128::from(self.den) * 1_000_000)
    }

    /// Millionths of a host unit at `steps`, rounded to the nearest (ties away from zero).
    pub fn micro_from_steps(&self, steps: i64) -> Option<i64> {
        div_round(i128::from(steps) * i128::from(self.den) * 1_000_000, i128::from(self.num))
    }
}

#[cfg(test)]
mod ratio_tests {
    use super::Ratio;

    #[test]
    fn unit_conversion_is_exact_and_rounds_to_nearest() {
        // A gantry with 80 steps per mm: 1 mm = 80 steps, 12.5 µm = 1 step.
        let mm = Ratio { num: 80, den: 1 };
        assert_eq!(mm.steps_from_micro(1_000_000), Some(80));
        assert_eq!(mm.steps_from_micro(12_500), Some(1));
        assert_eq!(mm.steps_from_micro(6_250), Some(1), "half a step rounds away from zero");
        assert_eq!(mm.steps_from_micro(-6_250), Some(-1));
        assert_eq!(mm.steps_from_micro(6_249), Some(0));
        assert_eq!(mm.micro_from_steps(-80), Some(-1_000_000));
        // A turntable: 200 steps × 16 microsteps × 90:1 gear per 360° = 800 steps per degree.
        let deg = Ratio { num: 200 * 16 * 90, den: 360 };
        assert_eq!(deg.steps_from_micro(360_000_000), Some(288_000));
        assert_eq!(deg.micro_from_steps(288_000), Some(360_000_000));
        // A ratio that is not a whole number of steps per unit: 1000 steps per 3 mm.
        let odd = Ratio { num: 1000, den: 3 };
        for steps in -10_000..10_000 {
            let back = odd.steps_from_micro(odd.micro_from_steps(steps).unwrap()).unwrap();
            assert_eq!(back, steps, "round trip");
        }
        assert_eq!(Ratio { num: 1, den: 0 }.steps_from_micro(1), None);
        assert_eq!(Ratio { num: u32::MAX, den: 1 }.steps_from_micro(i64::MAX), None);
    }
}

/// What a stepper axis moves, which fixes its host-side unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum AxisKind {
    /// Millimetres (gantry).
    Linear,
    /// Degrees (turntable); may be unlimited.
    Rotary,
}

/// A closed range of step positions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct StepRange {
    /// Lowest allowed position.
    pub min: i32,
    /// Highest allowed position.
    pub max: i32,
}

/// How an axis finds its reference position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum HomingMode {
    /// The axis is not homed; positions are relative to power-up.
    None,
    /// Move towards negative positions until the min limit switch.
    ToMinLimit,
    /// Move towards positive positions until the max limit switch.
    ToMaxLimit,
    /// Move forward until the index sensor.
    ToIndex,
}

/// Homing parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Homing {
    /// Which reference to seek.
    pub mode: HomingMode,
    /// Seek speed, steps per second.
    pub speed: u32,
    /// Steps to back off the switch after it triggers.
    pub backoff: u32,
    /// Position assigned to the axis once homed.
    pub position: i32,
}

/// A stepper axis: turntable or gantry (`Configure(Stepper)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct StepperConfig {
    /// Which axis, `0..capabilities.steppers`.
    pub axis: u8,
    /// Linear or rotary.
    pub kind: AxisKind,
    /// Steps per host unit (per millimetre or per degree).
    pub steps_per_unit: Ratio,
    /// Top speed, steps per second.
    pub max_speed: u32,
    /// Acceleration, steps per second squared.
    pub accel: u32,
    /// Soft limits; required for linear axes, `None` for an endless rotary axis.
    pub limits: Option<StepRange>,
    /// Homing procedure.
    pub homing: Homing,
    /// Invert the direction output.
    pub invert_dir: bool,
    /// Level of the driver-enable output that energises the motor.
    pub enable: Polarity,
    /// Limit switch at the negative end.
    pub limit_min: Input,
    /// Limit switch at the positive end.
    pub limit_max: Input,
    /// Index (home) sensor.
    pub index: Input,
}

/// A filter wheel (`Configure(FilterWheel)`), driven by its own stepper.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct FilterWheelConfig {
    /// Which wheel, `0..capabilities.filter_wheels`.
    pub wheel: u8,
    /// Number of filter positions, `2..=MAX_FILTER_SLOTS`.
    pub slots: u8,
    /// Motor steps per wheel revolution; at least one step per slot.
    pub steps_per_rev: u32,
    /// Top speed, steps per second.
    pub max_speed: u32,
    /// Acceleration, steps per second squared.
    pub accel: u32,
    /// Index sensor; required, the wheel homes on it.
    pub index: Input,
    /// Steps from the index mark to the centre of slot 0, `|offset| < steps_per_rev`.
    pub index_offset: i32,
    /// Invert the direction output.
    pub invert_dir: bool,
    /// Level of the driver-enable output.
    pub enable: Polarity,
}

/// A voice-coil synthesis channel (`Configure(VoiceCoil)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct VoiceCoilConfig {
    /// Which channel, `0..capabilities.voice_coils`.
    pub channel: u8,
    /// Output sample rate, `48_000..=192_000` Hz.
    pub sample_rate_hz: u32,
    /// Largest summed amplitude the channel may output, as a fraction of full scale
    /// (`u16::MAX` = full scale). Never zero.
    pub max_amplitude: u16,
}

/// A camera trigger output (`Configure(Camera)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct CameraConfig {
    /// Which output, `0..capabilities.cameras`.
    pub camera: u8,
    /// Trigger pulse width in ticks, used when a trigger item gives no exposure. Never zero.
    pub pulse_ticks: u32,
    /// Level of the trigger pulse.
    pub polarity: Polarity,
    /// Exposure-active (strobe) input from the camera, captured with its tick.
    pub exposure_input: Input,
    /// Shortest time between two trigger edges the camera accepts.
    pub min_interval_ticks: u32,
}

/// Device-wide safety settings (`Configure(Safety)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct SafetyConfig {
    /// Ticks without a `Heartbeat` (or any command) after which the device faults with
    /// `HeartbeatLost`: lasers off, galvos park, steppers stop. Between 10 ms and 60 s.
    pub heartbeat_timeout_ticks: u32,
}

/// One peripheral's configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum ConfigItem {
    /// A galvo pair.
    Galvo(GalvoConfig),
    /// A laser channel.
    Laser(LaserConfig),
    /// A stepper axis.
    Stepper(StepperConfig),
    /// A filter wheel.
    FilterWheel(FilterWheelConfig),
    /// A voice-coil channel.
    VoiceCoil(VoiceCoilConfig),
    /// A camera trigger.
    Camera(CameraConfig),
    /// Safety settings.
    Safety(SafetyConfig),
}

/// Every configuration field that can be refused, named as in the rig file.
#[allow(missing_docs)] // each variant's doc is its `name()`
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum ConfigField {
    GalvoIndex,
    GalvoXMinCode,
    GalvoXMaxCode,
    GalvoXZeroCode,
    GalvoXNanoradPerCode,
    GalvoYMinCode,
    GalvoYMaxCode,
    GalvoYZeroCode,
    GalvoYNanoradPerCode,
    GalvoParkX,
    GalvoParkY,
    LaserChannel,
    LaserWavelength,
    LaserMaxOnTicks,
    LaserWarmupTicks,
    StepperAxis,
    StepperStepsPerUnit,
    StepperMaxSpeed,
    StepperAccel,
    StepperLimits,
    StepperHomingMode,
    StepperHomingSpeed,
    StepperHomingPosition,
    FilterWheelIndex,
    FilterWheelSlots,
    FilterWheelStepsPerRev,
    FilterWheelMaxSpeed,
    FilterWheelAccel,
    FilterWheelIndexSensor,
    FilterWheelIndexOffset,
    VoiceCoilChannel,
    VoiceCoilSampleRate,
    VoiceCoilMaxAmplitude,
    CameraIndex,
    CameraPulseTicks,
    SafetyHeartbeatTimeout,
}

impl ConfigField {
    /// The field's dotted name, as written in a rig file (`galvo.x.min_code`).
    pub const fn name(self) -> &'static str {
        use ConfigField::*;
        match self {
            GalvoIndex => "galvo.galvo",
            GalvoXMinCode => "galvo.x.min_code",
            GalvoXMaxCode => "galvo.x.max_code",
            GalvoXZeroCode => "galvo.x.zero_code",
            GalvoXNanoradPerCode => "galvo.x.nanorad_per_code",
            GalvoYMinCode => "galvo.y.min_code",
            GalvoYMaxCode => "galvo.y.max_code",
            GalvoYZeroCode => "galvo.y.zero_code",
            GalvoYNanoradPerCode => "galvo.y.nanorad_per_code",
            GalvoParkX => "galvo.park.x",
            GalvoParkY => "galvo.park.y",
            LaserChannel => "laser.channel",
            LaserWavelength => "laser.wavelength_nm",
            LaserMaxOnTicks => "laser.max_on_ticks",
            LaserWarmupTicks => "laser.warmup_ticks",
            StepperAxis => "stepper.axis",
            StepperStepsPerUnit => "stepper.steps_per_unit",
            StepperMaxSpeed => "stepper.max_speed",
            StepperAccel => "stepper.accel",
            StepperLimits => "stepper.limits",
            StepperHomingMode => "stepper.homing.mode",
            StepperHomingSpeed => "stepper.homing.speed",
            StepperHomingPosition => "stepper.homing.position",
            FilterWheelIndex => "filter_wheel.wheel",
            FilterWheelSlots => "filter_wheel.slots",
            FilterWheelStepsPerRev => "filter_wheel.steps_per_rev",
            FilterWheelMaxSpeed => "filter_wheel.max_speed",
            FilterWheelAccel => "filter_wheel.accel",
            FilterWheelIndexSensor => "filter_wheel.index",
            FilterWheelIndexOffset => "filter_wheel.index_offset",
            VoiceCoilChannel => "voice_coil.channel",
            VoiceCoilSampleRate => "voice_coil.sample_rate_hz",
            VoiceCoilMaxAmplitude => "voice_coil.max_amplitude",
            CameraIndex => "camera.camera",
            CameraPulseTicks => "camera.pulse_ticks",
            SafetyHeartbeatTimeout => "safety.heartbeat_timeout_ticks",
        }
    }
}

/// Why a field was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum InvalidReason {
    /// The peripheral index is not below the device's count of that peripheral.
    NoSuchPeripheral {
        /// How many the device has.
        count: u8,
    },
    /// Zero is not allowed here.
    Zero,
    /// Below the smallest allowed value.
    TooSmall {
        /// Smallest allowed value.
        min: i64,
    },
    /// Above the largest allowed value.
    TooLarge {
        /// Largest allowed value.
        max: i64,
    },
    /// A range whose minimum is not below its maximum.
    EmptyRange,
    /// The value must lie inside another configured range and does not.
    OutsideRange {
        /// Lower bound.
        min: i64,
        /// Upper bound.
        max: i64,
    },
    /// The field must be present for this kind of peripheral.
    Required,
    /// The setting needs an input (limit switch, index sensor) that is configured as unused.
    NeedsInput,
}

/// A refused configuration: which field of which peripheral, and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct ConfigError {
    /// The refused field.
    pub field: ConfigField,
    /// Index of the peripheral (galvo, channel, axis, wheel, camera) it belongs to.
    pub index: u8,
    /// Why.
    pub reason: InvalidReason,
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{}[{}]: ", self.field.name(), self.index)?;
        match self.reason {
            InvalidReason::NoSuchPeripheral { count } => {
                write!(f, "the device has only {count} of these")
            }
            InvalidReason::Zero => f.write_str("must not be zero"),
            InvalidReason::TooSmall { min } => write!(f, "must be at least {min}"),
            InvalidReason::TooLarge { max } => write!(f, "must be at most {max}"),
            InvalidReason::EmptyRange => f.write_str("min must be below max"),
            InvalidReason::OutsideRange { min, max } => {
                write!(f, "must lie within {min}..={max}")
            }
            InvalidReason::Required => f.write_str("is required here"),
            InvalidReason::NeedsInput => f.write_str("needs an input that is configured unused"),
        }
    }
}

/// Highest step rate any axis may be configured for, steps per second.
pub const MAX_STEP_RATE: u32 = 500_000;
/// Allowed voice-coil sample rates, Hz.
pub const SAMPLE_RATE_RANGE: (u32, u32) = (48_000, 192_000);
/// Allowed laser wavelengths, nm.
pub const WAVELENGTH_RANGE: (u16, u16) = (200, 2_000);
/// Allowed heartbeat timeouts, milliseconds (converted with the device's tick rate).
pub const HEARTBEAT_RANGE_MS: (u32, u32) = (10, 60_000);

/// Accumulates the context of one peripheral's checks so each one is a single line.
struct Check {
    index: u8,
}

impl Check {
    fn that(&self, ok: bool, field: ConfigField, reason: InvalidReason) -> Result<(), ConfigError> {
        if ok {
            Ok(())
        } else {
            Err(ConfigError { field, index: self.index, reason })
        }
    }

    fn index(&self, field: ConfigField, count: u8) -> Result<(), ConfigError> {
        self.that(self.index < count, field, InvalidReason::NoSuchPeripheral { count })
    }

    fn nonzero(&self, value: u32, field: ConfigField) -> Result<(), ConfigError> {
        self.that(value != 0, field, InvalidReason::Zero)
    }

    fn between(&self, value: i64, min: i64, max: i64, field: ConfigField) -> Result<(), ConfigError> {
        self.that(value >= min, field, InvalidReason::TooSmall { min })?;
        self.that(value <= max, field, InvalidReason::TooLarge { max })
    }

    fn within(&self, value: i64, min: i64, max: i64, field: ConfigField) -> Result<(), ConfigError> {
        self.that((min..=max).contains(&value), field, InvalidReason::OutsideRange { min, max })
    }
}

fn ms_to_ticks(ms: u32, tick_hz: u32) -> i64 {
    i64::from(ms) * i64::from(tick_hz) / 1000
}

impl GalvoAxis {
    fn validate(&self, c: &Check, dac: DacKind, fields: [ConfigField; 4]) -> Result<(), ConfigError> {
        let [min_f, max_f, zero_f, scale_f] = fields;
        c.between(self.max_code.into(), 1, dac.max_code().into(), max_f)?;
        c.that(self.min_code < self.max_code, min_f, InvalidReason::EmptyRange)?;
        c.within(self.zero_code.into(), self.min_code.into(), self.max_code.into(), zero_f)?;
        c.that(self.nanorad_per_code != 0, scale_f, InvalidReason::Zero)
    }

    fn contains(&self, code: u16) -> bool {
        (self.min_code..=self.max_code).contains(&code)
    }
}

impl ConfigItem {
    /// Index of the peripheral this item configures (0 for device-wide settings).
    pub const fn index(&self) -> u8 {
        match self {
            ConfigItem::Galvo(g) => g.galvo,
            ConfigItem::Laser(l) => l.channel,
            ConfigItem::Stepper(s) => s.axis,
            ConfigItem::FilterWheel(w) => w.wheel,
            ConfigItem::VoiceCoil(v) => v.channel,
            ConfigItem::Camera(c) => c.camera,
            ConfigItem::Safety(_) => 0,
        }
    }

    /// Checks the item against the protocol's limits and the device's capabilities.
    /// Returns the first refused field.
    pub fn validate(&self, device: &DeviceInfo) -> Result<(), ConfigError> {
        use ConfigField as F;
        let caps = &device.capabilities;
        let c = Check { index: self.index() };
        match self {
            ConfigItem::Galvo(g) => {
                c.index(F::GalvoIndex, caps.galvos)?;
                let x = [F::GalvoXMinCode, F::GalvoXMaxCode, F::GalvoXZeroCode, F::GalvoXNanoradPerCode];
                let y = [F::GalvoYMinCode, F::GalvoYMaxCode, F::GalvoYZeroCode, F::GalvoYNanoradPerCode];
                g.x.validate(&c, g.dac, x)?;
                g.y.validate(&c, g.dac, y)?;
                let (xr, yr) = (&g.x, &g.y);
                let outside = |a: &GalvoAxis| InvalidReason::OutsideRange {
                    min: a.min_code.into(),
                    max: a.max_code.into(),
                };
                c.that(xr.contains(g.park.x), F::GalvoParkX, outside(xr))?;
                c.that(yr.contains(g.park.y), F::GalvoParkY, outside(yr))
            }
            ConfigItem::Laser(l) => {
                c.index(F::LaserChannel, caps.lasers)?;
                let (lo, hi) = WAVELENGTH_RANGE;
                c.between(l.wavelength_nm.into(), lo.into(), hi.into(), F::LaserWavelength)?;
                c.nonzero(l.max_on_ticks, F::LaserMaxOnTicks)?;
                c.between(l.warmup_ticks.into(), 0, l.max_on_ticks.into(), F::LaserWarmupTicks)
            }
            ConfigItem::Stepper(s) => {
                c.index(F::StepperAxis, caps.steppers)?;
                c.that(
                    s.steps_per_unit.num != 0 && s.steps_per_unit.den != 0,
                    F::StepperStepsPerUnit,
                    InvalidReason::Zero,
                )?;
                c.between(s.max_speed.into(), 1, MAX_STEP_RATE.into(), F::StepperMaxSpeed)?;
                c.nonzero(s.accel, F::StepperAccel)?;
                match (s.kind, s.limits) {
                    (AxisKind::Linear, None) => c.that(false, F::StepperLimits, InvalidReason::Required)?,
                    (_, Some(r)) => c.that(r.min < r.max, F::StepperLimits, InvalidReason::EmptyRange)?,
                    (AxisKind::Rotary, None) => {}
                }
                let h = &s.homing;
                let input = match h.mode {
                    HomingMode::None => return Ok(()),
                    HomingMode::ToMinLimit => s.limit_min,
                    HomingMode::ToMaxLimit => s.limit_max,
                    HomingMode::ToIndex => s.index,
                };
                c.that(input != Input::Unused, F::StepperHomingMode, InvalidReason::NeedsInput)?;
                c.between(h.speed.into(), 1, s.max_speed.into(), F::StepperHomingSpeed)?;
                if let Some(r) = s.limits {
                    c.within(h.position.into(), r.min.into(), r.max.into(), F::StepperHomingPosition)?;
                }
                Ok(())
            }
            ConfigItem::FilterWheel(w) => {
                c.index(F::FilterWheelIndex, caps.filter_wheels)?;
                c.between(w.slots.into(), 2, MAX_FILTER_SLOTS.into(), F::FilterWheelSlots)?;
                c.between(
                    w.steps_per_rev.into(),
                    w.slots.into(),
                    i32::MAX.into(),
                    F::FilterWheelStepsPerRev,
                )?;
                c.between(w.max_speed.into(), 1, MAX_STEP_RATE.into(), F::FilterWheelMaxSpeed)?;
                c.nonzero(w.accel, F::FilterWheelAccel)?;
                c.that(w.index != Input::Unused, F::FilterWheelIndexSensor, InvalidReason::Required)?;
                let spr = i64::from(w.steps_per_rev);
                c.between(w.index_offset.into(), 1 - spr, spr - 1, F::FilterWheelIndexOffset)
            }
            ConfigItem::VoiceCoil(v) => {
                c.index(F::VoiceCoilChannel, caps.voice_coils)?;
                let (lo, hi) = SAMPLE_RATE_RANGE;
                c.between(v.sample_rate_hz.into(), lo.into(), hi.into(), F::VoiceCoilSampleRate)?;
                c.that(v.max_amplitude != 0, F::VoiceCoilMaxAmplitude, InvalidReason::Zero)
            }
            ConfigItem::Camera(k) => {
                c.index(F::CameraIndex, caps.cameras)?;
                c.nonzero(k.pulse_ticks, F::CameraPulseTicks)
            }
            ConfigItem::Safety(s) => {
                let (lo, hi) = HEARTBEAT_RANGE_MS;
                let (lo, hi) = (ms_to_ticks(lo, device.tick_hz), ms_to_ticks(hi, device.tick_hz));
                c.between(s.heartbeat_timeout_ticks.into(), lo.max(1), hi, F::SafetyHeartbeatTimeout)
            }
        }
    }
}
