//! The bispectral gonioreflectometer's scene (thesis §4.4.1, figure 4.4): coated spheres on the
//! sample stage, seen by a monochrome camera behind a tunable filter, lit from the light arm
//! by a xenon source behind a second tunable filter or by a near-UV/blue LED of the filter
//! wheel. The spectra and materials are [`lightrig_pipelines::brrdf::spectra`]'s closed forms.
//!
//! Geometry (orthographic camera along −z, the light arm turning about the vertical image
//! axis): the light comes from `(sin a, 0, cos a)` for the arm's angle `a` (0: beside the
//! camera). Two spheres stand on the stage's axis one above the other, the orange clear coat
//! (sharp highlight) on top and the fluorescent yellow below: turning the stage turns them in
//! place. With `[plan] sample = "spectralon"` a flat Spectralon target faces the camera instead
//! (the spectral calibration session).
//!
//! What lights the sample follows the step: the wheel's slot names it (`led-NNN`: that LED;
//! `white`: the xenon through the light filter at the step's `meta.host.light_filter_nm`;
//! `dark` or between slots: nothing), and the camera filter is tuned to
//! `meta.host.camera_filter_nm`. The frames are grey (the same value in R, G and B).

use std::collections::HashMap;
use std::sync::Mutex;

use lightrig_host::rigfile::RigFile;
use lightrig_pipelines::brrdf::spectra::{camera_value, ccd, led, sums, xenon, Lctf, Material, Sums};

use crate::camera::{RigState, Scene};

/// What stands on the stage.
#[derive(Debug, Clone, PartialEq)]
pub enum Sample {
    /// The two coated spheres, radius in pixels.
    Spheres { radius: f64 },
    /// A flat Spectralon target filling the view.
    Spectralon,
}

/// What every pixel of a frame shares: the wheel's slot and the light and camera filters'
/// wavelengths (as bits).
type FrameKey = (Option<u8>, u64, u64);

/// The scene.
#[derive(Debug)]
pub struct BispectralScene {
    pub width: u32,
    pub height: u32,
    pub sample: Sample,
    /// Top sphere, bottom sphere, and the Spectralon target.
    pub materials: [Material; 3],
    pub light_filter: Lctf,
    pub camera_filter: Lctf,
    /// The light arm's axis.
    pub light_axis: u8,
    /// The filter wheel and its slot names.
    pub wheel: u8,
    pub slots: Vec<String>,
    /// Radiance scale: the camera value of Spectralon lit head-on through the white slot at
    /// 550 nm on both filters is this.
    pub scale: f64,
    /// The wavelength integrals of each material per (wheel slot, light filter, camera filter):
    /// every pixel of a frame shares them.
    sums: Mutex<HashMap<FrameKey, [Sums; 3]>>,
}

impl BispectralScene {
    /// The scene for `rig` (the light arm named `light-arm`, else the second rotary axis; the
    /// first filter wheel), `width × height` pixels.
    pub fn new(rig: &RigFile, width: u32, height: u32) -> Self {
        let rotary: Vec<_> =
            rig.steppers.iter().filter(|s| s.kind == lightrig_protocol::config::AxisKind::Rotary).collect();
        let light_axis = rig
            .stepper_named("light-arm")
            .map(|s| s.axis)
            .or_else(|| rotary.get(1).map(|s| s.axis))
            .unwrap_or(1);
        let wheel = rig.filter_wheels.first();
        let sample = match rig.plan.get("sample").and_then(|v| v.as_str()) {
            Some("spectralon") => Sample::Spectralon,
            _ => Sample::Spheres { radius: f64::from(height.min(width / 2)) * 0.21 },
        };
        let mut s = BispectralScene {
            width,
            height,
            sample,
            materials: [Material::orange_coat(), Material::fluorescent_yellow(), Material::spectralon()],
            light_filter: Lctf::default(),
            camera_filter: Lctf::default(),
            light_axis,
            wheel: wheel.map_or(0, |w| w.wheel),
            slots: wheel.map(|w| w.filters.clone()).unwrap_or_default(),
            scale: 1.0,
            sums: Mutex::new(HashMap::new()),
        };
        let n = [0.0, 0.0, 1.0];
        let reference = camera_value(
            &Material::spectralon(),
            &|nm| xenon(nm) * s.light_filter.transmission(550.0, nm),
            &|nm| s.camera_filter.transmission(550.0, nm) * ccd(nm),
            n,
            n,
            n,
        );
        s.scale = 1.0 / reference;
        s
    }

    /// The sphere (0 top, 1 bottom) and unit normal seen at pixel `(x, y)`, or the target's.
    pub fn surface(&self, x: u32, y: u32) -> Option<(usize, [f64; 3])> {
        match self.sample {
            Sample::Spectralon => Some((0, [0.0, 0.0, 1.0])),
            Sample::Spheres { radius } => {
                let (px, py) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
                let cx = f64::from(self.width) / 2.0;
                for (k, cy) in
                    [f64::from(self.height) * 0.27, f64::from(self.height) * 0.73].into_iter().enumerate()
                {
                    let (dx, dy) = ((px - cx) / radius, (cy - py) / radius);
                    let r2 = dx * dx + dy * dy;
                    if r2 < 1.0 {
                        return Some((k, [dx, dy, (1.0 - r2).sqrt()]));
                    }
                }
                None
            }
        }
    }

    /// The light's direction for `state`.
    pub fn light_dir(&self, state: &RigState) -> [f64; 3] {
        let a = state.axes.get(usize::from(self.light_axis)).copied().unwrap_or(0.0).to_radians();
        [a.sin(), 0.0, a.cos()]
    }

    fn host_nm(state: &RigState, key: &str) -> Option<f64> {
        state.meta.get("host").and_then(|h| h.get(key)).and_then(|v| v.as_f64())
    }
}

impl Scene for BispectralScene {
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn radiance(&self, x: u32, y: u32, state: &RigState) -> [f64; 3] {
        let Some((k, n)) = self.surface(x, y) else { return [0.0; 3] };
        let k = if self.sample == Sample::Spectralon { 2 } else { k };
        let slot = state.filters.get(usize::from(self.wheel)).copied().flatten();
        let name = slot.and_then(|s| self.slots.get(usize::from(s))).map(String::as_str).unwrap_or("dark");
        let Some(camera_nm) = Self::host_nm(state, "camera_filter_nm") else { return [0.0; 3] };
        let light_nm = Self::host_nm(state, "light_filter_nm");
        let wi = self.light_dir(state);
        let wo = [0.0, 0.0, 1.0];
        let material = &self.materials[k];
        let key = (slot, light_nm.unwrap_or(0.0).to_bits(), camera_nm.to_bits());
        let cached = self.sums.lock().ok().and_then(|c| c.get(&key).map(|v| v[k]));
        let frame_sums = match cached {
            Some(s) => s,
            None => {
                let camera = |nm: f64| self.camera_filter.transmission(camera_nm, nm) * ccd(nm);
                let led_nm = name.strip_prefix("led-").and_then(|c| c.parse::<f64>().ok());
                let source = |nm: f64| match (led_nm, name, light_nm) {
                    (Some(c), _, _) => led(c, nm),
                    (None, "white", Some(l)) => xenon(nm) * self.light_filter.transmission(l, nm),
                    _ => 0.0,
                };
                let all = self.materials.each_ref().map(|m| sums(m, &source, &camera));
                if let Ok(mut c) = self.sums.lock() {
                    c.insert(key, all);
                }
                all[k]
            }
        };
        let v = frame_sums.value(material, wi, wo, n);
        [v * self.scale; 3]
    }
}
