//! Device emulators for trying the hardware drivers without hardware:
//!
//! ```text
//! cargo run --release -p haptic-bridge --example emulator -- hapticmaster [SECONDS]
//! cargo run --release -p haptic-bridge --example emulator -- serial [SECONDS]
//! cargo run --release -p haptic-bridge --example emulator -- serial-bridge URL SESSION
//! ```
//!
//! `serial-bridge` runs the HBP/1 emulator and the bridge's serial driver in this one process
//! over a pseudo-terminal pair (where another process cannot open the pair's slave, as in some
//! sandboxes) and streams to the hapticd session at URL, printing the bridge summary as JSON.
//!
//! Each prints where it listens (a TCP address, or the pseudo-terminal path to pass as
//! `--serial-port`) and the `haptic-bridge` flags that make its hand press the built-in `lv`
//! scene (6 mm along -x at 10 mm/s, a 3 s hold), then runs for SECONDS (default 60).

use std::time::Duration;

use std::sync::Arc;

use haptic_bridge::hapticmaster::Emulator;
use haptic_bridge::serial::{EmulatorFaults, SerialDevice, SerialEmulator, SerialParams};
use haptic_bridge::sim::Script;
use haptic_bridge::{BridgeConfig, HapticDevice, MonotonicClock};
use serialport::{SerialPort, TTYPort};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let which = args.next().unwrap_or_default();
    let seconds: f64 = if which == "serial-bridge" {
        0.0
    } else {
        args.next().map_or(Ok(60.0), |s| s.parse())?
    };
    let press = |start_m, direction| Script::Press {
        start_m,
        direction,
        depth_m: 0.006,
        speed_m_per_s: 0.01,
        hold_s: 3.0,
    };
    match which.as_str() {
        "hapticmaster" => {
            // Device frame: z vertical, x fore-aft. With the default axes y,z,x the scene point
            // is (y, z, x) + offset: device (0.45, 0.014, 0) + (0, 0, -0.455) = scene
            // (0.014, 0, -0.005), the LV press start; device -y is scene -x.
            let emu = Emulator::spawn(
                press([0.45, 0.014, 0.0], [0.0, -1.0, 0.0]),
                Duration::from_millis(500),
            )?;
            println!("hapticmaster emulator on {}", emu.addr());
            println!(
                "haptic-bridge --driver hapticmaster --hm-addr {} --offset-m 0,0,-0.455 ...",
                emu.addr()
            );
            std::thread::sleep(Duration::from_secs_f64(seconds));
        }
        "serial" => {
            let (mut master, slave) = TTYPort::pair()?;
            master.set_timeout(Duration::ZERO)?;
            let path = slave.name().ok_or("the pseudo-terminal has no path")?;
            let emu = SerialEmulator::spawn(
                master,
                press([0.014, 0.0, -0.005], [-1.0, 0.0, 0.0]),
                EmulatorFaults::default(),
            )?;
            println!("HBP/1 emulator on {path}");
            println!("haptic-bridge --driver serial --serial-port {path} --baud 0 ...");
            std::thread::sleep(Duration::from_secs_f64(seconds));
            println!("emulator log: {:?}", emu.stop().watchdog_trips);
            drop(slave);
        }
        "serial-bridge" => {
            let url = seconds_or_url(&which)?;
            let mut rest = std::env::args().skip(3);
            let session = rest.next().ok_or("serial-bridge URL SESSION")?;
            let (mut master, mut slave) = TTYPort::pair()?;
            master.set_timeout(Duration::ZERO)?;
            slave.set_timeout(Duration::ZERO)?;
            let emu = SerialEmulator::spawn(
                master,
                press([0.014, 0.0, -0.005], [-1.0, 0.0, 0.0]),
                EmulatorFaults::default(),
            )?;
            let dev = SerialDevice::open(
                Box::new(slave) as Box<dyn SerialPort>,
                Arc::new(MonotonicClock::new()),
                SerialParams::default(),
            )?;
            let spec = dev.spec().clone();
            let mut config = BridgeConfig::new(url, session, &spec);
            // The emulator's press lasts 4.8 s; hardware drivers never "finish" on their own.
            config.max_duration = Some(Duration::from_secs(5));
            let rt = tokio::runtime::Runtime::new()?;
            let (_tx, rx) = tokio::sync::watch::channel(false);
            let report = rt.block_on(haptic_bridge::run(
                Box::new(dev),
                Arc::new(MonotonicClock::new()),
                config,
                rx,
            ))?;
            drop(emu);
            println!("{}", serde_json::to_string(&report.summary)?);
        }
        _ => {
            eprintln!("usage: emulator hapticmaster|serial [SECONDS] | serial-bridge URL SESSION");
            std::process::exit(2);
        }
    }
    Ok(())
}

/// The URL argument of `serial-bridge`.
fn seconds_or_url(_which: &str) -> Result<String, Box<dyn std::error::Error>> {
    Ok(std::env::args().nth(2).ok_or("serial-bridge URL SESSION")?)
}
