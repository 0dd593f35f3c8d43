//! The rig description file: the examples in docs/rigs, exact unit conversions, and the
//! error for each kind of mistake, with its file, line and key.

use std::path::{Path, PathBuf};

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::rigfile::{ticks_from_ms, ticks_from_us, Connect, FrameSource, Method, RigFile};
use lightrig_protocol::config::{
    AxisKind, ConfigItem, DacKind, HomingMode, Input, Polarity, Ratio, StepRange, StepperConfig,
};
use lightrig_protocol::session::DeviceInfo;

const RIGS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/rigs");

/// Lines 1–3 of every inline rig below.
const HEAD: &str = "[rig]\nname = \"test\"\nmethod = \"disco\"\n";

fn parse(body: &str) -> RigFile {
    RigFile::parse(&format!("{HEAD}{body}"), Path::new("rig.toml")).unwrap_or_else(|e| panic!("{e}"))
}

fn parse_err(body: &str) -> String {
    match RigFile::parse(&format!("{HEAD}{body}"), Path::new("rig.toml")) {
        Ok(_) => panic!("parsed:\n{body}"),
        Err(e) => e.to_string(),
    }
}

fn items(body: &str) -> Vec<ConfigItem> {
    parse(body).config_items(&virtual_device_info()).unwrap_or_else(|e| panic!("{e}"))
}

fn config_err(body: &str) -> String {
    config_err_with(body, &virtual_device_info())
}

fn config_err_with(body: &str, info: &DeviceInfo) -> String {
    match parse(body).config_items(info) {
        Ok(items) => panic!("converted: {items:?}"),
        Err(e) => e.to_string(),
    }
}

fn example(name: &str) -> RigFile {
    RigFile::load(&Path::new(RIGS).join(name)).unwrap_or_else(|e| panic!("{e}"))
}

fn stepper(items: &[ConfigItem], axis: u8) -> StepperConfig {
    items
        .iter()
        .find_map(|i| match i {
            ConfigItem::Stepper(s) if s.axis == axis => Some(*s),
            _ => None,
        })
        .expect("stepper item")
}

const GANTRY: &str = "[[stepper]]
axis = 0
kind = \"linear\"
steps_per_unit = \"80\"
max_speed = 100
accel = 500
limits = [-200.0, 200.0]
homing = { mode = \"min\", speed = 20, backoff = 2, position = -200 }
limit_min = \"low\"
";

#[test]
fn every_example_parses_and_converts_for_the_virtual_device() {
    let mut names: Vec<PathBuf> = std::fs::read_dir(RIGS)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    names.sort();
    let stems: Vec<_> = names.iter().map(|p| p.file_stem().unwrap().to_str().unwrap().to_string()).collect();
    assert_eq!(stems, ["bispectral", "brdf-display", "disco", "fluorescent-immersion", "lls-gantry"]);
    let info = virtual_device_info();
    for path in &names {
        let rig = RigFile::load(path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(rig.connect, Connect::Virtual, "{}", path.display());
        let items = rig.config_items(&info).unwrap_or_else(|e| panic!("{e}"));
        let expected = rig.galvos.len()
            + rig.lasers.len()
            + rig.steppers.len()
            + rig.filter_wheels.len()
            + rig.voice_coils.len()
            + rig.cameras.len()
            + usize::from(rig.safety.is_some());
        assert_eq!(items.len(), expected, "{}", path.display());
        for item in &items {
            assert_eq!(item.validate(&info), Ok(()));
        }
        assert!(!rig.plan.is_empty(), "{}: every example has a [plan]", path.display());
    }
}

#[test]
fn examples_have_their_methods_and_peripherals() {
    let disco = example("disco.toml");
    assert_eq!(disco.method, Method::Disco);
    // Three lasers and the registration spotlights (a fourth switched output, no interlock).
    assert_eq!((disco.galvos.len(), disco.lasers.len(), disco.steppers.len()), (1, 4, 1));
    let nm: Vec<u16> = disco.lasers.iter().map(|l| l.wavelength_nm).collect();
    assert_eq!(nm, [635, 532, 476, 550]);
    assert_eq!(disco.galvos[0].dac, DacKind::Dac8563);
    assert!(disco.lasers[..3].iter().all(|l| l.interlock == Input::Wired(Polarity::ActiveLow)));
    assert_eq!(disco.plan["registration"].as_str(), disco.lasers[3].name.as_deref());
    assert_eq!(example("fluorescent-immersion.toml").method, Method::FluorescentImmersion);
    let bispectral = example("bispectral.toml");
    assert_eq!(bispectral.method, Method::Bispectral);
    assert_eq!(bispectral.filter_wheels[0].slots, 7);
    assert!(bispectral.plan["tunable_filter"].is_table());
    assert_eq!(example("lls-gantry.toml").method, Method::LinearLightSource);
    let display = example("brdf-display.toml");
    assert_eq!(display.method, Method::BrdfDisplay);
    assert!(display.voice_coils.iter().all(|v| v.sample_rate_hz == 48_000));
}

#[test]
fn disco_example_converts_exactly() {
    let items = example("disco.toml").config_items(&virtual_device_info()).unwrap();
    let ConfigItem::Safety(s) = items[0] else { panic!("safety first: {:?}", items[0]) };
    assert_eq!(s.heartbeat_timeout_ticks, 250_000);
    let ConfigItem::Galvo(g) = items[1] else { panic!("{:?}", items[1]) };
    assert_eq!((g.x.nanorad_per_code, g.y.nanorad_per_code), (10_653, -10_653), "10.6526 µrad, rounded");
    assert_eq!((g.park.x, g.park.y, g.settle_ticks), (8192, 8192, 300));
    let ConfigItem::Laser(red) = items[2] else { panic!("{:?}", items[2]) };
    assert_eq!((red.warmup_ticks, red.max_on_ticks), (5_000, 600_000_000));
    let t = stepper(&items, 0);
    assert_eq!(t.steps_per_unit, Ratio { num: 800, den: 1 }, "200*16*90/360 reduced");
    assert_eq!((t.max_speed, t.accel, t.limits), (16_000, 32_000, None));
    assert_eq!((t.homing.mode, t.homing.speed), (HomingMode::ToIndex, 4_000));
}

#[test]
fn gantry_limits_and_homing_convert_to_steps() {
    let items = items(GANTRY);
    let s = stepper(&items, 0);
    assert_eq!(s.kind, AxisKind::Linear);
    assert_eq!(s.limits, Some(StepRange { min: -16_000, max: 16_000 }), "±200 mm at 80 steps/mm");
    assert_eq!((s.max_speed, s.accel), (8_000, 40_000));
    assert_eq!((s.homing.speed, s.homing.backoff, s.homing.position), (1_600, 160, -16_000));
    assert_eq!(s.limit_min, Input::Wired(Polarity::ActiveLow));
    assert_eq!((s.limit_max, s.index, s.enable), (Input::Unused, Input::Unused, Polarity::ActiveHigh));

    let rig = parse(GANTRY);
    assert_eq!(rig.stepper_steps(0, 12.5), Ok(1_000));
    assert_eq!(rig.stepper_steps(0, -0.00625), Ok(-1), "half a step rounds away from zero");
    assert_eq!(
        rig.stepper_steps(0, 250.0).unwrap_err().to_string(),
        "rig.toml:10: stepper[0].limits: 250 mm is outside the limits -200..=200 mm"
    );
    assert_eq!(
        rig.stepper_steps(3, 0.0).unwrap_err().to_string(),
        "rig.toml:4: stepper: no [[stepper]] has axis = 3; configured axes: [0]"
    );
}

#[test]
fn ratio_strings_are_exact() {
    let rig = |spu: &str| {
        format!(
            "[[stepper]]\naxis = 0\nkind = \"rotary\"\nsteps_per_unit = {spu}\nmax_speed = 10\naccel = 10\n\
             limits = [-180, 180]\n"
        )
    };
    let s = stepper(&items(&rig("\"3200/360\"")), 0);
    assert_eq!(s.steps_per_unit, Ratio { num: 80, den: 9 });
    assert_eq!(s.limits, Some(StepRange { min: -1_600, max: 1_600 }));
    assert_eq!(s.max_speed, 89, "10 deg/s × 80/9 = 88.9 steps/s");
    let s = stepper(&items(&rig("\"200 * 16 * 90 / 360\"")), 0);
    assert_eq!(s.steps_per_unit, Ratio { num: 800, den: 1 });
    assert_eq!(s.limits, Some(StepRange { min: -144_000, max: 144_000 }));
    let s = stepper(&items(&rig("\"1000/3*2\"")), 0);
    assert_eq!(s.steps_per_unit, Ratio { num: 500, den: 3 }, "a/b*c divides by the product b*c");
    let s = stepper(&items(&rig("80")), 0);
    assert_eq!(s.steps_per_unit, Ratio { num: 80, den: 1 }, "a plain integer");

    assert_eq!(
        parse_err(&rig("1.8")),
        "rig.toml:7: stepper[0].steps_per_unit: 1.8 is a float; write an integer or an exact ratio string \
         such as \"3200/360\" or \"200*16*90/360\""
    );
    assert_eq!(
        parse_err(&rig("\"3200/0\"")),
        "rig.toml:7: stepper[0].steps_per_unit: \"3200/0\" has a zero factor; steps per unit must be positive"
    );
    assert_eq!(
        parse_err(&rig("\"3200:360\"")),
        "rig.toml:7: stepper[0].steps_per_unit: \"3200:360\" is not a ratio; write a product of positive \
         integers, optionally divided by another, e.g. \"80\", \"3200/360\" or \"200*16*90/360\""
    );
}

#[test]
fn times_round_to_the_nearest_tick() {
    assert_eq!(ticks_from_ms(0.2, 1_000_000), Some(200));
    assert_eq!(ticks_from_us(0.1, 10_000_000), Some(1));
    assert_eq!(ticks_from_us(2.5, 1_000_000), Some(3), "ties away from zero");
    assert_eq!(ticks_from_us(-1.0, 1_000_000), None);

    let body = "[safety]\nheartbeat_timeout_ms = 12.5\n[[laser]]\nchannel = 0\nwavelength_nm = 532\n\
                warmup_ms = 0.2\nmax_on_s = 1.5\ninterlock = \"unused\"\n[[camera]]\ncamera = 0\n\
                pulse_us = 33.3\nmin_interval_us = 16666.7\n";
    let mut info = virtual_device_info();
    for (tick_hz, expected) in [
        (1_000_000, [12_500, 200, 1_500_000, 33, 16_667]),
        (168_000_000, [2_100_000, 33_600, 252_000_000, 5_594, 2_800_006]),
    ] {
        info.tick_hz = tick_hz;
        let items = parse(body).config_items(&info).unwrap();
        let got = match items[..] {
            [ConfigItem::Safety(s), ConfigItem::Laser(l), ConfigItem::Camera(c)] => [
                s.heartbeat_timeout_ticks,
                l.warmup_ticks,
                l.max_on_ticks,
                c.pulse_ticks,
                c.min_interval_ticks,
            ],
            _ => panic!("{items:?}"),
        };
        assert_eq!(got, expected, "at {tick_hz} Hz");
    }
}

#[test]
fn galvo_voice_coil_and_filter_wheel_convert() {
    let body = "[[galvo]]
galvo = 0
dac = \"mcu\"
x = { min_code = 0, max_code = 4095, zero_code = 2048, urad_per_code = 170.4 }
y = { min_code = 100, max_code = 4000, zero_code = 2000, urad_per_code = -0.0015 }
settle_us = 250
[[voice_coil]]
channel = 1
sample_rate_hz = 96000
max_amplitude = 0.5
[[filter_wheel]]
wheel = 0
filters = [\"none\", \"BP450\", \"BP550\", \"BP650\"]
steps_per_rev = 3200
max_speed = 1.5
accel = 4
index = \"high\"
index_offset = -12
";
    let items = items(body);
    let ConfigItem::Galvo(g) = items[0] else { panic!() };
    assert_eq!((g.dac, g.x.nanorad_per_code, g.y.nanorad_per_code), (DacKind::McuDac, 170_400, -2));
    assert_eq!((g.park.x, g.park.y), (2048, 2000), "park defaults to the zero codes");
    let ConfigItem::VoiceCoil(v) = items[2] else { panic!("{items:?}") };
    assert_eq!((v.channel, v.sample_rate_hz, v.max_amplitude), (1, 96_000, 32_768), "0.5 × 65535 rounded up");
    let ConfigItem::FilterWheel(w) = items[1] else { panic!("{items:?}") };
    assert_eq!((w.slots, w.max_speed, w.accel, w.index_offset), (4, 4_800, 12_800, -12));

    let rig = parse(body);
    assert_eq!(rig.filter_slot(0, "BP550"), Ok(2));
    assert_eq!(
        rig.filter_slot(0, "bp550").unwrap_err().to_string(),
        "rig.toml:16: filter_wheel[0].filters: no slot is named \"bp550\"; did you mean \"BP550\"? slots: \
         \"none\", \"BP450\", \"BP550\", \"BP650\""
    );
}

#[test]
fn device_and_camera_sources() {
    let rig = RigFile::parse(
        &format!(
            "{HEAD}[device]\nconnect = \"serial:/dev/ttyACM0@921600\"\n[[camera]]\ncamera = 0\n\
             pulse_us = 100\n\
             source = {{ kind = \"directory\", path = \"frames\", pattern = \"img_{{frame:06}}.png\" }}\n"
        ),
        Path::new("/lab/rigs/gantry.toml"),
    )
    .unwrap();
    assert_eq!(rig.connect, Connect::Serial { port: "/dev/ttyACM0".into(), baud: 921_600 });
    let source = rig.camera_source(0).unwrap();
    assert_eq!(
        source,
        &FrameSource::Directory { dir: "/lab/rigs/frames".into(), pattern: "img_{frame:06}.png".into() }
    );
    assert_eq!(source.frame_path(17), Some(PathBuf::from("/lab/rigs/frames/img_000017.png")));
    assert_eq!(parse("").connect, Connect::Virtual, "virtual by default");
    assert_eq!(parse("[device]\nconnect = \"usb\"\n").connect, Connect::Usb);
    assert_eq!(
        parse("[device]\nconnect = \"serial:COM3\"\n").connect,
        Connect::Serial { port: "COM3".into(), baud: 115_200 }
    );
    assert_eq!(
        parse_err("[device]\nconnect = \"tcp:10.0.0.2\"\n"),
        "rig.toml:5: device.connect: unknown value \"tcp:10.0.0.2\"; valid values: \"virtual\", \"usb\", \
         \"serial:PATH\" or \"serial:PATH@BAUD\" (e.g. \"serial:/dev/ttyACM0@115200\")"
    );
    assert_eq!(
        parse_err("[[camera]]\ncamera = 0\npulse_us = 100\n\
                   source = { kind = \"directory\", path = \"f\", pattern = \"x.png\" }\n"),
        "rig.toml:7: camera[0].source.pattern: \"x.png\" needs exactly one {frame} or {frame:0N} placeholder \
         (N digits, zero-padded), e.g. \"img_{frame:06}.png\""
    );
    // A virtual camera's gamma and a camera's response file (relative to the rig file).
    let rig = RigFile::parse(
        &format!(
            "{HEAD}[[camera]]\ncamera = 0\npulse_us = 100\nsource = {{ kind = \"virtual\", gamma = 2.2 }}\n\
             response = \"cam0.json\"\n"
        ),
        Path::new("/lab/rigs/gantry.toml"),
    )
    .unwrap();
    assert_eq!(rig.camera_source(0).unwrap(), &FrameSource::Virtual { gamma: 2.2 });
    assert_eq!(rig.cameras[0].response.as_deref(), Some(Path::new("/lab/rigs/cam0.json")));
    assert_eq!(parse("[[camera]]\ncamera = 0\npulse_us = 100\n").cameras[0].response, None);
    // A GenICam camera.
    let rig = parse(
        "[[camera]]\ncamera = 0\npulse_us = 100\n\
         source = { kind = \"genicam\", address = \"192.168.1.20\", trigger = \"Line0\", pixel_format = \"Mono16\" }\n",
    );
    assert_eq!(
        rig.camera_source(0).unwrap(),
        &FrameSource::Genicam(lightrig_host::rigfile::GenicamSource {
            address: "192.168.1.20".into(),
            trigger: "Line0".into(),
            activation: None,
            pixel_format: Some("Mono16".into()),
            exposure_us: None,
            buffers: 16,
        })
    );
    assert_eq!(
        parse_err("[[camera]]\ncamera = 0\npulse_us = 100\nsource = { kind = \"genicam\" }\n"),
        "rig.toml:7: camera[0].source.address: required for kind = \"genicam\": the camera's address \
         (\"192.168.1.20\") or its Aravis id (`lightrig devices` lists them)"
    );
    assert_eq!(
        parse_err("[[camera]]\ncamera = 0\npulse_us = 100\nsource = { kind = \"virtual\", address = \"x\" }\n"),
        "rig.toml:7: camera[0].source.address: only for kind = \"genicam\" (a GenICam camera read through Aravis)"
    );
    assert_eq!(
        parse_err("[[camera]]\ncamera = 0\npulse_us = 100\nsource = { kind = \"virtual\", gamma = 9 }\n"),
        "rig.toml:7: camera[0].source.gamma: must be in 0.2..=5.0 (1 is a linear camera, 2.2 a display gamma)"
    );
    assert_eq!(
        parse_err(
            "[[camera]]\ncamera = 0\npulse_us = 100\n\
                   source = { kind = \"directory\", path = \"f\", pattern = \"x{frame}.png\", gamma = 2 }\n"
        ),
        "rig.toml:7: camera[0].source.gamma: only for kind = \"virtual\": a real camera's curve is its \
         `response` file"
    );
}

#[test]
fn unknown_keys_name_the_line_and_the_valid_keys() {
    assert_eq!(
        parse_err(&GANTRY.replace("max_speed", "max_sped")),
        "rig.toml:8: stepper[0].max_sped: unknown key; did you mean \"max_speed\"? Valid keys here: axis, \
         name, kind, steps_per_unit, max_speed, accel, limits, homing, invert_dir, enable, limit_min, \
         limit_max, index"
    );
    assert_eq!(
        parse_err(&GANTRY.replace("speed = 20", "sped = 20")),
        "rig.toml:11: stepper[0].homing.sped: unknown key; did you mean \"speed\"? Valid keys here: mode, \
         speed, backoff, position"
    );
    assert_eq!(
        parse_err("[[lasers]]\nchannel = 0\n"),
        "rig.toml:4: lasers: unknown key; did you mean \"laser\"? Valid keys here: rig, device, safety, \
         galvo, laser, stepper, filter_wheel, voice_coil, camera, plan"
    );
    assert_eq!(
        parse_err("[device]\nport = \"/dev/ttyACM0\"\n"),
        "rig.toml:5: device.port: unknown key; valid keys here: connect"
    );
}

#[test]
fn wrong_enum_strings_list_the_valid_values() {
    assert_eq!(
        parse_err(&GANTRY.replace("\"linear\"", "\"linar\"")),
        "rig.toml:6: stepper[0].kind: unknown value \"linar\"; did you mean \"linear\"? Valid values: \
         \"linear\", \"rotary\""
    );
    assert_eq!(
        parse_err(&GANTRY.replace("mode = \"min\"", "mode = \"home\"")),
        "rig.toml:11: stepper[0].homing.mode: unknown value \"home\"; valid values: \"min\", \"max\", \
         \"index\", \"none\""
    );
    assert_eq!(
        parse_err(&GANTRY.replace("limit_min = \"low\"", "limit_min = \"active-low\"")),
        "rig.toml:12: stepper[0].limit_min: unknown value \"active-low\"; did you mean \"low\"? Valid \
         values: \"high\", \"low\", \"unused\""
    );
    assert_eq!(
        RigFile::parse("[rig]\nname = \"x\"\nmethod = \"DISCO\"\n", Path::new("r.toml"))
            .unwrap_err()
            .to_string(),
        "r.toml:3: rig.method: unknown value \"DISCO\"; did you mean \"disco\"? Valid values: \"disco\", \
         \"fluorescent-immersion\", \"bispectral\", \"linear-light-source\", \"brdf-display\""
    );
}

#[test]
fn missing_required_keys_point_at_their_table() {
    let laser = "[[laser]]\nchannel = 0\nwavelength_nm = 635\nmax_on_s = 60\ninterlock = \"low\"\n";
    let second = "[[laser]]\nchannel = 1\nwavelength_nm = 532\ninterlock = \"low\"\n";
    assert_eq!(
        parse_err(&format!("{laser}{second}")),
        "rig.toml:9: laser[1].max_on_s: required key is missing (longest continuous on-time in s)"
    );
    assert_eq!(
        parse_err("[[stepper]]\naxis = 0\nkind = \"rotary\"\nsteps_per_unit = 800\naccel = 1\n"),
        "rig.toml:4: stepper[0].max_speed: required key is missing (top speed in mm/s or deg/s)"
    );
    assert_eq!(
        RigFile::parse("[device]\nconnect = \"virtual\"\n", Path::new("r.toml")).unwrap_err().to_string(),
        "r.toml: rig: required key is missing ([rig] with name and method)"
    );
    assert_eq!(
        parse_err(&GANTRY.replace("homing = { mode = \"min\", speed = 20,", "homing = { mode = \"min\",")),
        "rig.toml:11: stepper[0].homing.speed: required when homing.mode = \"min\": the seek speed in mm/s"
    );
    assert_eq!(
        parse_err(
            "[[filter_wheel]]\nwheel = 0\nsteps_per_rev = 3200\nmax_speed = 1\naccel = 1\nindex = \"low\"\n"
        ),
        "rig.toml:4: filter_wheel[0]: give slots = N or filters = [\"name\", …] (one name per slot)"
    );
}

#[test]
fn wrong_types_and_values_are_refused_at_parse() {
    assert_eq!(
        parse_err(&GANTRY.replace("max_speed = 100", "max_speed = \"fast\"")),
        "rig.toml:8: stepper[0].max_speed: expected a number, found string \"fast\""
    );
    assert_eq!(
        parse_err(&GANTRY.replace("accel = 500", "accel = -500")),
        "rig.toml:9: stepper[0].accel: must not be negative"
    );
    assert_eq!(
        parse_err(&GANTRY.replace("limits = [-200.0, 200.0]", "limits = [-200.0]")),
        "rig.toml:10: stepper[0].limits: must be [min, max] in mm: two numbers, not 1"
    );
    assert_eq!(
        parse_err("[[laser]]\nchannel = 8\nwavelength_nm = 635\nmax_on_s = 60\ninterlock = \"low\"\n"),
        "rig.toml:5: laser[0].channel: must be at most 7: the protocol has at most 8 laser channels"
    );
    assert_eq!(
        parse_err("[[voice_coil]]\nchannel = 0\nsample_rate_hz = 48000\nmax_amplitude = 1.5\n"),
        "rig.toml:7: voice_coil[0].max_amplitude: must be at most 1.0 (full scale)"
    );
    assert_eq!(
        parse_err("[[filter_wheel]]\nwheel = 0\nslots = 4\nfilters = [\"a\", \"b\", \"c\"]\n\
                   steps_per_rev = 3200\nmax_speed = 1\naccel = 1\nindex = \"low\"\n"),
        "rig.toml:7: filter_wheel[0].filters: lists 3 filters but slots = 4; give one name per slot (or drop \
         slots)"
    );
    assert_eq!(
        parse_err("[safety]\nheartbeat_timeout_ms = 100\nheartbeat_timeout_ms = 200\n"),
        "rig.toml:6: invalid TOML: duplicate key \"heartbeat_timeout_ms\"; each key may appear once per table"
    );
    assert_eq!(
        parse_err("[safety]\nheartbeat_timeout_ms = \n"),
        "rig.toml:5: invalid TOML: string values must be quoted, expected literal string"
    );
}

#[test]
fn duplicate_indexes_and_names_are_refused() {
    let laser = |ch: u8, name: &str| {
        format!(
            "[[laser]]\nchannel = {ch}\nname = \"{name}\"\nwavelength_nm = 635\nmax_on_s = 60\n\
             interlock = \"low\"\n"
        )
    };
    assert_eq!(
        parse_err(&format!("{}{}{}", laser(0, "red"), laser(1, "green"), laser(0, "blue"))),
        "rig.toml:17: laser[2].channel: channel 0 is already configured by laser[0] at line 4; each channel \
         may appear once"
    );
    assert_eq!(
        parse_err(&format!("{}{}", laser(0, "red"), laser(1, "red"))),
        "rig.toml:12: laser[1].name: name \"red\" is already used by laser[0]; names must be unique"
    );
}

#[test]
fn values_beyond_the_device_limits_are_reported_in_file_units() {
    // The error the brief's example names: 80 steps/mm caps a gantry at 6250 mm/s.
    assert_eq!(
        config_err(&GANTRY.replace("max_speed = 100", "max_speed = 7000")),
        "rig.toml:8: stepper[0].max_speed: must be at most 6250 mm/s (500000 steps/s at 80 steps/mm)"
    );
    assert_eq!(
        config_err(&GANTRY.replace("max_speed = 100", "max_speed = 1e12")),
        "rig.toml:8: stepper[0].max_speed: must be at most 6250 mm/s (500000 steps/s at 80 steps/mm)"
    );
    assert_eq!(
        config_err(&GANTRY.replace("speed = 20", "speed = 200")),
        "rig.toml:11: stepper[0].homing.speed: must be at most max_speed (100 mm/s)"
    );
    assert_eq!(
        config_err(&GANTRY.replace("accel = 500", "accel = 0.001")),
        "rig.toml:9: stepper[0].accel: must be at least 0.0125 mm/s² (1 step/s² at 80 steps/mm)"
    );
    assert_eq!(
        config_err(&GANTRY.replace("position = -200", "position = -250")),
        "rig.toml:11: stepper[0].homing.position: must lie within the limits -200..=200 mm"
    );
    let laser = "[[laser]]\nchannel = 0\nwavelength_nm = 635\nmax_on_s = 5000\ninterlock = \"low\"\n";
    assert_eq!(
        config_err(laser),
        "rig.toml:7: laser[0].max_on_s: 5000 s is too long: at 1000000 Hz the device counts at most \
         4294967295 ticks (4294.967295 s)"
    );
    assert_eq!(
        config_err(&laser.replace("635", "150").replace("5000", "60")),
        "rig.toml:6: laser[0].wavelength_nm: must lie within 200..=2000 nm"
    );
    assert_eq!(
        config_err("[safety]\nheartbeat_timeout_ms = 5\n"),
        "rig.toml:5: safety.heartbeat_timeout_ms: must lie within 10..=60000 ms"
    );
    assert_eq!(
        config_err("[[voice_coil]]\nchannel = 0\nsample_rate_hz = 44100\nmax_amplitude = 0.5\n"),
        "rig.toml:6: voice_coil[0].sample_rate_hz: must lie within 48000..=192000 Hz"
    );
    assert_eq!(
        config_err(
            "[[filter_wheel]]\nwheel = 0\nslots = 6\nsteps_per_rev = 3200\nmax_speed = 200\naccel = 4\n\
             index = \"low\"\n"
        ),
        "rig.toml:8: filter_wheel[0].max_speed: must be at most 156.25 rev/s (500000 steps/s at 3200 \
         steps/rev)"
    );
}

#[test]
fn an_example_with_a_mistake_points_at_its_line() {
    let text = std::fs::read_to_string(Path::new(RIGS).join("lls-gantry.toml")).unwrap();
    let text = text.replace("max_speed = 100 ", "max_speed = 7000");
    let rig = RigFile::parse(&text, Path::new("docs/rigs/lls-gantry.toml")).unwrap();
    assert_eq!(
        rig.config_items(&virtual_device_info()).unwrap_err().to_string(),
        "docs/rigs/lls-gantry.toml:25: stepper[0].max_speed: must be at most 6250 mm/s (500000 steps/s at 80 \
         steps/mm)"
    );
}

#[test]
fn capabilities_exceeded_name_what_the_device_has() {
    let laser = |ch: u8| {
        format!("[[laser]]\nchannel = {ch}\nwavelength_nm = 635\nmax_on_s = 60\ninterlock = \"low\"\n")
    };
    assert_eq!(
        config_err(&(0..5).map(laser).collect::<String>()),
        "rig.toml:25: laser[4].channel: the device has only 4 lasers (channels 0..=3)"
    );
    let camera = "[[camera]]\ncamera = 1\npulse_us = 100\n";
    let mut info = virtual_device_info();
    info.capabilities.cameras = 1;
    assert_eq!(
        config_err_with(camera, &info),
        "rig.toml:5: camera[0].camera: the device has only 1 camera output (camera 0)"
    );
    let mut info = virtual_device_info();
    info.capabilities.galvos = 0;
    let galvo = "[[galvo]]\ngalvo = 0\ndac = \"dac8563\"\n\
                 x = { min_code = 0, max_code = 65535, zero_code = 32768, urad_per_code = 10 }\n\
                 y = { min_code = 0, max_code = 65535, zero_code = 32768, urad_per_code = 10 }\n\
                 settle_us = 300\n";
    assert_eq!(
        config_err_with(galvo, &info),
        "rig.toml:5: galvo[0].galvo: the device has no galvo pairs; remove this table or connect a device \
         that has galvo pairs"
    );
}

#[test]
fn device_side_refusals_map_back_to_the_rig_key() {
    let laser =
        "[[laser]]\nchannel = 0\nwavelength_nm = 635\nwarmup_ms = 50\nmax_on_s = 0\ninterlock = \"low\"\n";
    assert_eq!(
        config_err(laser),
        "rig.toml:8: laser[0].max_on_s: must not be zero: it is the longest the laser may stay on"
    );
    assert_eq!(
        config_err(&laser.replace("max_on_s = 0", "max_on_s = 0.01")),
        "rig.toml:7: laser[0].warmup_ms: 50 ms is longer than max_on_s (0.01 s): the laser would fault \
         before it is ready"
    );
    assert_eq!(
        config_err(&GANTRY.replace("limit_min = \"low\"", "limit_max = \"low\"")),
        "rig.toml:11: stepper[0].homing.mode: mode \"min\" seeks the limit_min input, but limit_min is \
         \"unused\"; wire it (limit_min = \"high\" or \"low\") or choose another mode"
    );
    assert_eq!(
        config_err(&GANTRY.replace("limits = [-200.0, 200.0]\n", "")),
        "rig.toml:4: stepper[0].limits: required for a linear axis: limits = [min, max] in mm"
    );
    assert_eq!(
        config_err(&GANTRY.replace("[-200.0, 200.0]", "[200.0, -200.0]")),
        "rig.toml:10: stepper[0].limits: min (200 mm) must be below max (-200 mm)"
    );
    let galvo = "[[galvo]]\ngalvo = 0\ndac = \"mcu\"\n\
                 x = { min_code = 0, max_code = 4095, zero_code = 2048, urad_per_code = 170 }\n\
                 y = { min_code = 0, max_code = 4095, zero_code = 5000, urad_per_code = 170 }\n\
                 park = [2048, 2048]\nsettle_us = 300\n";
    assert_eq!(
        config_err(galvo),
        "rig.toml:8: galvo[0].y.zero_code: must lie within min_code..=max_code (0..=4095)"
    );
    assert_eq!(
        config_err(&galvo.replace("max_code = 4095, zero_code = 2048", "max_code = 65535, zero_code = 2048")),
        "rig.toml:7: galvo[0].x.max_code: must be at most 4095, the largest code of dac = \"mcu\""
    );
    assert_eq!(
        config_err(
            &galvo.replace("zero_code = 5000", "zero_code = 2048").replace("[2048, 2048]", "[2048, 4096]")
        ),
        "rig.toml:9: galvo[0].park[1]: y = 4096 must lie within y.min_code..=y.max_code (0..=4095)"
    );
    assert_eq!(
        config_err(
            "[[filter_wheel]]\nwheel = 0\nslots = 6\nsteps_per_rev = 3200\nmax_speed = 1\naccel = 4\n\
             index = \"unused\"\n"
        ),
        "rig.toml:10: filter_wheel[0].index: must be wired (\"high\" or \"low\"): the wheel homes on its \
         index sensor"
    );
    assert_eq!(
        config_err("[[camera]]\ncamera = 0\npulse_us = 0.2\n"),
        "rig.toml:6: camera[0].pulse_us: 0.2 µs rounds to 0 ticks at 1000000 Hz; must not be zero"
    );
}

#[test]
fn errors_carry_their_parts() {
    let e = RigFile::parse(&format!("{HEAD}[[laser]]\nchannel = 0\n"), Path::new("docs/rigs/x.toml"))
        .unwrap_err();
    assert_eq!(e.path, Path::new("docs/rigs/x.toml"));
    assert_eq!(e.line, Some(4));
    assert_eq!(e.key, "laser[0].wavelength_nm");
    assert_eq!(e.message, "required key is missing (nominal wavelength in nm)");
    let e = RigFile::load(Path::new("/nonexistent/rig.toml")).unwrap_err();
    assert_eq!((e.line, e.key.as_str()), (None, ""));
    assert!(e.to_string().starts_with("/nonexistent/rig.toml: cannot read the rig file: "), "{e}");
    let rig = example("bispectral.toml");
    assert_eq!(
        rig.line_of("plan.tunable_filter.range_nm"),
        rig.line_of("plan.tunable_filter").map(|l| l + 4)
    );
    assert_eq!(rig.filter_slot(0, "led-400"), Ok(2));
    assert_eq!(rig.stepper_named("light-arm").map(|s| s.axis), Some(1));
    assert_eq!(rig.stepper_steps(1, -168.0), Ok(-149_333), "-168° at 8000/9 steps/deg");
}
