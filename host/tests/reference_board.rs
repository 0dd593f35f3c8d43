//! Every rig file in docs/rigs/ runs on the reference board as wired: its configuration fits
//! the NUCLEO-G474RE's peripherals (`lightrig_firmware::boards`, the counts the board's
//! firmware reports and its pin map documents), at the board's tick rate and coil sample rate.

use std::path::{Path, PathBuf};

use lightrig_firmware::boards::{NUCLEO_G474RE, NUCLEO_G474RE_TICK_HZ, NUCLEO_G474RE_VOICE_COIL_HZ};
use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::rigfile::RigFile;
use lightrig_protocol::config::ConfigItem;
use lightrig_protocol::session::{BoardId, Capabilities, DeviceInfo};

fn rigs() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/rigs"))
}

/// What a NUCLEO-G474RE says in its Hello (the controller's own buffer sizes as the virtual
/// device's: the same `Controller`).
fn nucleo() -> DeviceInfo {
    let v = virtual_device_info();
    DeviceInfo {
        board: BoardId::NucleoG474re,
        tick_hz: NUCLEO_G474RE_TICK_HZ,
        capabilities: Capabilities {
            sequence_buffer: v.capabilities.sequence_buffer,
            event_queue: v.capabilities.event_queue,
            link_window: v.capabilities.link_window,
            ..NUCLEO_G474RE
        },
        ..v
    }
}

fn rig_files() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(rigs())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    files.sort();
    files
}

#[test]
fn every_shipped_rig_file_fits_the_reference_board() {
    let files = rig_files();
    let names: Vec<&str> = files.iter().filter_map(|p| p.file_stem()?.to_str()).collect();
    assert_eq!(names, ["bispectral", "brdf-display", "disco", "fluorescent-immersion", "lls-gantry"]);
    let info = nucleo();
    for path in &files {
        let rig = RigFile::load(path).unwrap();
        let items = rig.config_items(&info).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        for item in &items {
            if let ConfigItem::VoiceCoil(c) = item {
                assert_eq!(c.sample_rate_hz, NUCLEO_G474RE_VOICE_COIL_HZ, "{}", path.display());
            }
        }
    }
}

/// What each published rig needs at once, as its shipped file configures it: the board has
/// each (the counts are the board's, so this fails if a count drops below a rig's need).
#[test]
fn the_reference_board_offers_what_each_rig_needs_at_once() {
    let info = nucleo();
    let count = |file: &str| -> [usize; 5] {
        let rig = RigFile::load(&rigs().join(file)).unwrap();
        let items = rig.config_items(&info).unwrap();
        let n = |f: fn(&ConfigItem) -> bool| items.iter().filter(|i| f(i)).count();
        [
            n(|i| matches!(i, ConfigItem::Galvo(_))),
            n(|i| matches!(i, ConfigItem::Laser(_))),
            n(|i| matches!(i, ConfigItem::Stepper(_))),
            n(|i| matches!(i, ConfigItem::FilterWheel(_))),
            n(|i| matches!(i, ConfigItem::VoiceCoil(_))),
        ]
    };
    // galvo pairs, lasers, steppers, filter wheels, voice coils
    assert_eq!(count("disco.toml"), [1, 4, 1, 0, 0]);
    assert_eq!(count("bispectral.toml"), [0, 0, 2, 1, 0]);
    assert_eq!(count("lls-gantry.toml"), [0, 2, 1, 0, 0]);
    assert_eq!(count("brdf-display.toml"), [0, 0, 0, 0, 2]);
    assert_eq!(count("fluorescent-immersion.toml"), [1, 1, 1, 0, 0]);
    // DISCO's registration spotlights are its fourth switched output (`[plan] registration`).
    let c = NUCLEO_G474RE;
    assert_eq!(
        (c.galvos, c.lasers, c.steppers, c.filter_wheels, c.voice_coils, c.cameras),
        (1, 4, 2, 1, 2, 1)
    );
}

/// The check bites: a peripheral beyond the board's is refused at its key and line.
#[test]
fn a_rig_file_needing_more_than_the_board_has_is_refused_where_it_says_so() {
    let path = rigs().join("disco.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let extra = "\n[[laser]]\nchannel = 4\nname = \"uv\"\nwavelength_nm = 405\nwarmup_ms = 5\nmax_on_s = 600\nenable = \"high\"\ninterlock = \"unused\"\n";
    let rig = RigFile::parse(&format!("{text}{extra}"), Path::new("disco-plus.toml")).unwrap();
    let e = rig.config_items(&nucleo()).unwrap_err().to_string();
    assert!(e.contains("disco-plus.toml") && e.contains("laser[4].channel") && e.contains("only 4"), "{e}");
    let line = text.lines().count() + 3;
    assert!(e.contains(&format!(":{line}")), "{e}");
}
