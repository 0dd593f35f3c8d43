//! lightrig rig controller on the NUCLEO-G474RE (STM32G474RE): the firmware's `Controller` and
//! `Rig` over USB (vendor bulk interface and CDC-ACM), with the board's pins behind the
//! `hal` traits. Pin map and wiring: docs/boards/nucleo-g474re.md.

#![no_std]
#![no_main]

mod board;
mod inputs;
mod safety;
mod slots;
mod step;
mod trigger;
mod voice;
#[cfg(feature = "xy2-100")]
mod xy2;

/// The flash layout shared with the bootloader and the build script.
#[allow(dead_code)]
mod layout {
    include!("../layout.rs");
}

use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_futures::select::{select4, Either4};
use embassy_stm32::dac::{DacChannel, ValueArray};
use embassy_stm32::flash::Flash;
use embassy_stm32::gpio::{Flex, Input, Level, Output, Pull, Speed};
use embassy_stm32::mode::Async;
use embassy_stm32::peripherals::{RNG, USB};
use embassy_stm32::rcc::{mux, Hsi48Config, Pll, PllMul, PllPreDiv, PllRDiv, PllSource, Sysclk};
use embassy_stm32::rng::Rng;
#[cfg(not(feature = "xy2-100"))]
use embassy_stm32::spi::{self, Spi};
#[cfg(not(feature = "xy2-100"))]
use embassy_stm32::time::Hertz;
use embassy_stm32::usb::Driver;
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, dma, peripherals, rng, usb, Config};
use embassy_time::{with_timeout, Duration, Instant, Timer};
use embassy_usb::class::cdc_acm::{self, CdcAcmClass};
use embassy_usb::driver::{Direction, EndpointAddress, EndpointIn, EndpointOut};
use embassy_usb::{Builder, UsbDevice};
#[cfg(not(feature = "xy2-100"))]
use embedded_hal::spi::SpiDevice;
#[cfg(not(feature = "xy2-100"))]
use embedded_hal_bus::spi::ExclusiveDevice;
use lightrig_firmware::boards::{NUCLEO_G474RE, NUCLEO_G474RE_TICK_HZ};
use lightrig_firmware::controller::EmbassyClock;
#[cfg(feature = "xy2-100")]
use lightrig_firmware::galvo::Xy2Gpio;
#[cfg(not(feature = "xy2-100"))]
use lightrig_firmware::galvo::{SpiDacGalvo, SpiDacKind};
use lightrig_firmware::timer_schedule::{lookahead_tick, wake_tick};
use lightrig_firmware::Controller;
use lightrig_protocol::session::{BoardId, DeviceInfo, Version};
use lightrig_protocol::{MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH};
use static_cell::StaticCell;

use crate::board::{now_ticks, Motor, Nucleo, SafeOutput, LOOKAHEAD_TICKS};
use crate::slots::Slots;
use crate::step::{StepPulse, StepTimer};
use crate::trigger::Trigger;

bind_interrupts!(struct Irqs {
    USB_LP => usb::InterruptHandler<USB>;
    RNG => rng::InterruptHandler<RNG>;
    DMA1_CHANNEL1 => dma::InterruptHandler<peripherals::DMA1_CH1>;
    DMA1_CHANNEL2 => dma::InterruptHandler<peripherals::DMA1_CH2>;
});

/// USB ids and interface layout the host's `UsbTransport` expects (host/src/transport/usb.rs).
const USB_VID: u16 = 0x1209;
const USB_PID: u16 = 0x4C52;
const USB_EP_OUT: usize = 0x01;
const USB_EP_IN: usize = 0x01;
const USB_PACKET: u16 = 64;
/// Link retransmission timeout in ticks (1 µs): a USB round trip is ~1-2 ms.
const RTO_TICKS: u64 = 20_000;
/// The loop wakes at least this often, to feed the watchdog and service the board.
const MAX_SLEEP: Duration = Duration::from_millis(50);
/// A frame the host does not collect within this time is dropped (the link resends it), so an
/// abandoned port cannot stall the rig's poll, and with it the heartbeat watchdog.
const WRITE_TIMEOUT: Duration = Duration::from_millis(10);
/// This firmware's version when the active slot holds no signed image (flashed by probe).
const FIRMWARE: Version = Version { major: 0, minor: 1, patch: 0 };
/// Independent watchdog: resets the MCU (lasers go high-impedance) if the loop stops.
const WATCHDOG_US: u32 = 500_000;

type UsbDrv = Driver<'static, USB>;

// The tick rate the host is told is the one embassy-time counts.
const _: () = assert!(embassy_time::TICK_HZ == NUCLEO_G474RE_TICK_HZ as u64);

fn clocks() -> Config {
    let mut config = Config::default();
    // 168 MHz from HSI16 (no crystal needed): 16 / 4 × 84 / 2. A multiple of 48 kHz (voice
    // coils) and of 1 MHz (ticks); USB runs from HSI48 trimmed to the host's SOF by the CRS.
    config.rcc.pll = Some(Pll {
        source: PllSource::HSI,
        prediv: PllPreDiv::DIV4,
        mul: PllMul::MUL84,
        divp: None,
        divq: None,
        divr: Some(PllRDiv::DIV2),
    });
    config.rcc.sys = Sysclk::PLL1_R;
    config.rcc.boost = true;
    config.rcc.hsi48 = Some(Hsi48Config { sync_from_usb: true });
    config.rcc.mux.clk48sel = mux::Clk48sel::HSI48;
    config
}

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    // Before anything else: safety outputs high-impedance (they are at reset; make sure).
    safety::release_outputs();
    let reset_cause = safety::reset_cause();
    let p = embassy_stm32::init(clocks());
    defmt::info!("lightrig NUCLEO-G474RE, reset cause {}", defmt::Debug2Format(&reset_cause));

    let mut watchdog = IndependentWatchdog::new(p.IWDG, WATCHDOG_US);
    watchdog.unleash();

    // Boot id: must differ at every start (it is the link's boot nonce).
    let mut rng = Rng::new(p.RNG, Irqs);
    let boot_id = rng.next_u32();
    let uid = embassy_stm32::uid::uid();
    let serial =
        uid.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3));

    // Galvos: DAC8563 on SPI1, mode 1 (data latched on SCLK falling edges), 10 MHz.
    #[cfg(not(feature = "xy2-100"))]
    let galvo = {
        let mut spi_config = spi::Config::default();
        spi_config.mode = spi::MODE_1;
        spi_config.frequency = Hertz(10_000_000);
        let spi = Spi::new_blocking_txonly(p.SPI1, p.PA5, p.PA7, spi_config);
        let sync = Output::new(p.PB6, Level::High, Speed::VeryHigh);
        let mut dac_spi = match ExclusiveDevice::new_no_delay(spi, sync) {
            Ok(d) => d,
            Err(_) => defmt::panic!("SPI1 chip select"),
        };
        init_dac8563(&mut dac_spi);
        SpiDacGalvo::new(dac_spi, SpiDacKind::Dac8563)
    };
    // Galvos (feature `xy2-100`): XY2-100 on PC9-PC12, DMA2 channel 1 paced by TIM7.
    #[cfg(feature = "xy2-100")]
    let galvo = Xy2Gpio::new(xy2::Xy2Port::new(p.PC10, p.PC11, p.PC12, p.PC9, p.TIM7, p.DMA2_CH1));

    let trigger = Trigger::new(Flex::new(p.PA10));
    // The step pulses' one-pulse timers (step.rs programs them): taken so nothing else can.
    let _step_timers = (p.TIM3, p.TIM15, p.TIM17);
    // Pin map: docs/boards/nucleo-g474re.md (the same counts as `boards::NUCLEO_G474RE`).
    let mut board = Nucleo {
        galvo,
        lasers: [
            SafeOutput::new(Flex::new(p.PB5)),
            SafeOutput::new(Flex::new(p.PC7)),
            SafeOutput::new(Flex::new(p.PC4)),
            SafeOutput::new(Flex::new(p.PC5)),
        ],
        interlocks: [
            Input::new(p.PC8, Pull::None),
            Input::new(p.PA9, Pull::None),
            Input::new(p.PC2, Pull::None),
            Input::new(p.PC3, Pull::None),
        ],
        trigger,
        _exposure: inputs::exposure_pin(Flex::new(p.PB10)),
        steppers: [
            Motor {
                step: StepPulse::new(Flex::new(p.PC6), StepTimer::Tim3),
                dir: Output::new(p.PA8, Level::Low, Speed::High),
                enable: SafeOutput::new(Flex::new(p.PA1)),
                limit_min: Some(Input::new(p.PC0, Pull::None)),
                limit_max: Some(Input::new(p.PC1, Pull::None)),
                index: Some(Input::new(p.PB0, Pull::None)),
            },
            Motor {
                step: StepPulse::new(Flex::new(p.PB9), StepTimer::Tim17),
                dir: Output::new(p.PB12, Level::Low, Speed::High),
                enable: SafeOutput::new(Flex::new(p.PB11)),
                limit_min: Some(Input::new(p.PA0, Pull::None)),
                limit_max: Some(Input::new(p.PB2, Pull::None)),
                index: Some(Input::new(p.PB7, Pull::None)),
            },
        ],
        wheel: Motor {
            step: StepPulse::new(Flex::new(p.PB14), StepTimer::Tim15),
            dir: Output::new(p.PB13, Level::Low, Speed::High),
            enable: SafeOutput::new(Flex::new(p.PB15)),
            limit_min: None,
            limit_max: None,
            index: Some(Input::new(p.PB1, Pull::None)),
        },
        voice: voice::VoiceOutputs::new(),
        slots: Slots::new(Flash::new_blocking(p.FLASH)),
    };
    inputs::init();

    // Voice coils: DAC1 channel 1 (PA4) and DAC2 channel 1 (PA6), both paced by TIM6, which is
    // stopped until a stream starts: both DMAs begin at their rings' first slot in lockstep.
    let coil0 =
        DacChannel::new_triggered(p.DAC1, p.DMA1_CH1, embassy_stm32::triggers::TIM6_TRGO, Irqs, p.PA4);
    let coil1 =
        DacChannel::new_triggered(p.DAC2, p.DMA1_CH2, embassy_stm32::triggers::TIM6_TRGO, Irqs, p.PA6);
    spawner.spawn(voice_coil_dma(coil0, 0).expect("spawn voice-coil task 0: pool size 2"));
    spawner.spawn(voice_coil_dma(coil1, 1).expect("spawn voice-coil task 1: pool size 2"));

    // USB: vendor bulk interface 0 (EP 0x01 OUT, 0x81 IN), then CDC-ACM (interfaces 1-2).
    let driver = Driver::new(p.USB, Irqs, p.PA12, p.PA11);
    static SERIAL: StaticCell<heapless::String<16>> = StaticCell::new();
    let serial_str = SERIAL.init(hex16(serial));
    let mut usb_config = embassy_usb::Config::new(USB_VID, USB_PID);
    usb_config.manufacturer = Some("lightrig");
    usb_config.product = Some("lightrig NUCLEO-G474RE");
    usb_config.serial_number = Some(serial_str.as_str());
    usb_config.max_power = 100;
    usb_config.max_packet_size_0 = 64;
    usb_config.device_class = 0xEF;
    usb_config.device_sub_class = 0x02;
    usb_config.device_protocol = 0x01;
    usb_config.composite_with_iads = true;

    static CONFIG_DESC: StaticCell<[u8; 256]> = StaticCell::new();
    static BOS_DESC: StaticCell<[u8; 64]> = StaticCell::new();
    static CONTROL_BUF: StaticCell<[u8; 64]> = StaticCell::new();
    static CDC_STATE: StaticCell<cdc_acm::State> = StaticCell::new();
    let mut builder = Builder::new(
        driver,
        usb_config,
        CONFIG_DESC.init([0; 256]),
        BOS_DESC.init([0; 64]),
        &mut [],
        CONTROL_BUF.init([0; 64]),
    );
    let (mut bulk_out, mut bulk_in) = {
        let mut function = builder.function(0xFF, 0, 0);
        let mut interface = function.interface();
        let mut alt = interface.alt_setting(0xFF, 0, 0, None);
        let out =
            alt.endpoint_bulk_out(Some(EndpointAddress::from_parts(USB_EP_OUT, Direction::Out)), USB_PACKET);
        let inp =
            alt.endpoint_bulk_in(Some(EndpointAddress::from_parts(USB_EP_IN, Direction::In)), USB_PACKET);
        (out, inp)
    };
    let cdc = CdcAcmClass::new(&mut builder, CDC_STATE.init(cdc_acm::State::new()), USB_PACKET);
    let (mut cdc_tx, mut cdc_rx) = cdc.split();
    let usb = builder.build();
    spawner.spawn(usb_task(usb).expect("spawn USB task: pool size 1, spawned once"));

    // The version the active slot's signed image says (one sent over the link); the crate's
    // own for a firmware flashed through the probe.
    let firmware = board.slots.running().map_or(FIRMWARE, |i| i.version);
    let info = DeviceInfo {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
        firmware,
        board: BoardId::NucleoG474re,
        serial,
        tick_hz: NUCLEO_G474RE_TICK_HZ,
        reset_cause,
        boot_id,
        capabilities: NUCLEO_G474RE,
    };
    defmt::info!("boot id {=u32:08x}, serial {=u64:016x}", boot_id, serial);
    let mut ctl = Controller::new(EmbassyClock, board, info, RTO_TICKS);

    let mut vendor_buf = [0u8; USB_PACKET as usize];
    let mut cdc_buf = [0u8; USB_PACKET as usize];
    let mut frame = [0u8; MAX_FRAME];
    // Frames go to the interface the host last spoke on.
    let mut reply_on_cdc = false;
    loop {
        watchdog.pet();
        let now = Instant::now();
        // The rig's work is woken for LOOKAHEAD_TICKS early (see the look-ahead poll below).
        let wake = wake_tick(ctl.link().next_deadline(), ctl.rig().next_due(), LOOKAHEAD_TICKS)
            .map_or(now + MAX_SLEEP, |t| Instant::from_ticks(t).min(now + MAX_SLEEP));
        let event = select4(
            read_vendor(&mut bulk_out, &mut vendor_buf),
            read_cdc(&mut cdc_rx, &mut cdc_buf),
            Timer::at(wake),
            inputs::WAKE.wait(),
        )
        .await;
        match event {
            Either4::First(n) => {
                reply_on_cdc = false;
                ctl.receive(&vendor_buf[..n]);
            }
            Either4::Second(n) => {
                reply_on_cdc = true;
                ctl.receive(&cdc_buf[..n]);
            }
            Either4::Third(()) | Either4::Fourth(()) => {}
        }
        ctl.poll();
        // Look-ahead: the rig's next due tick, if it is at most LOOKAHEAD_TICKS away, is polled
        // now, at that tick. The trigger arms its compare for it (exact edge); other outputs
        // wait for it in the board. Then the ordinary poll hands the events to the link.
        if let Some(t) = lookahead_tick(ctl.rig().next_due(), now_ticks(), LOOKAHEAD_TICKS) {
            ctl.rig_mut().poll(t);
            ctl.poll();
        }
        ctl.rig_mut().board_mut().service(now_ticks());
        while let Some(n) = ctl.poll_transmit(&mut frame) {
            let sent = if reply_on_cdc {
                with_timeout(WRITE_TIMEOUT, write_cdc(&mut cdc_tx, &frame[..n])).await
            } else {
                with_timeout(WRITE_TIMEOUT, write_vendor(&mut bulk_in, &frame[..n])).await
            };
            if sent.is_err() {
                // The host is not reading; the link retransmits once it is back.
                break;
            }
        }
        if ctl.wants_reset() {
            // An update is marked (the host has the answer that says so), or a swapped-in
            // firmware was not confirmed in time: the bootloader swaps at the reset.
            defmt::info!("resetting into the bootloader");
            safety::release_outputs();
            cortex_m::peripheral::SCB::sys_reset();
        }
    }
}

#[cfg(not(feature = "xy2-100"))]
/// DAC8563 start-up: reset, LDAC pins ignored (each write updates its output at once, as the
/// frames in `galvo.rs` expect), internal 2.5 V reference on (gain 2: 0-5 V).
fn init_dac8563(spi: &mut impl SpiDevice) {
    const RESET: [u8; 3] = [0x28, 0x00, 0x01];
    const LDAC_OFF: [u8; 3] = [0x30, 0x00, 0x03];
    const REFERENCE_ON: [u8; 3] = [0x38, 0x00, 0x01];
    for frame in [RESET, LDAC_OFF, REFERENCE_ON] {
        if spi.write(&frame).is_err() {
            defmt::error!("DAC8563 init: SPI write failed");
        }
    }
}

fn hex16(v: u64) -> heapless::String<16> {
    let mut s = heapless::String::new();
    for i in (0..16).rev() {
        let digit = b"0123456789ABCDEF"[((v >> (4 * i)) & 0xF) as usize];
        let _ = s.push(char::from(digit));
    }
    s
}

async fn read_vendor(ep: &mut impl EndpointOut, buf: &mut [u8]) -> usize {
    loop {
        match ep.read(buf).await {
            Ok(n) if n > 0 => return n,
            Ok(_) => {}
            Err(_) => ep.wait_enabled().await,
        }
    }
}

async fn read_cdc(rx: &mut cdc_acm::Receiver<'static, UsbDrv>, buf: &mut [u8]) -> usize {
    loop {
        match rx.read_packet(buf).await {
            Ok(n) if n > 0 => return n,
            Ok(_) => {}
            Err(_) => rx.wait_connection().await,
        }
    }
}

/// One frame as bulk packets; a frame that fills its last packet gets a zero-length packet so
/// the host's read returns now.
async fn write_vendor(ep: &mut impl EndpointIn, data: &[u8]) -> Result<(), ()> {
    for chunk in data.chunks(USB_PACKET as usize) {
        ep.write(chunk).await.map_err(|_| ())?;
    }
    if data.len().is_multiple_of(USB_PACKET as usize) {
        ep.write(&[]).await.map_err(|_| ())?;
    }
    Ok(())
}

async fn write_cdc(tx: &mut cdc_acm::Sender<'static, UsbDrv>, data: &[u8]) -> Result<(), ()> {
    for chunk in data.chunks(USB_PACKET as usize) {
        tx.write_packet(chunk).await.map_err(|_| ())?;
    }
    if data.len().is_multiple_of(USB_PACKET as usize) {
        tx.write_packet(&[]).await.map_err(|_| ())?;
    }
    Ok(())
}

#[embassy_executor::task]
async fn usb_task(mut usb: UsbDevice<'static, UsbDrv>) -> ! {
    usb.run().await
}

/// Runs the circular DMA that feeds a coil's DAC from its ring; never completes.
#[embassy_executor::task(pool_size = 2)]
async fn voice_coil_dma(mut dac: DacChannel<'static, Async>, coil: usize) {
    dac.write(ValueArray::Bit12Left(voice::ring(coil)), true).await;
    defmt::error!("voice-coil {} DMA stopped", coil);
}
