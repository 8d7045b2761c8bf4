//! The hardware drivers against their emulators: the HapticMaster TCP driver against the
//! [`hapticmaster::Emulator`] on `127.0.0.1:0`, the serial (HBP/1) driver against the
//! [`SerialEmulator`] over pseudo-terminal pairs (`TTYPort::pair()`, serialised: the pair is
//! not thread-safe), each alone and inside the whole bridge against an in-process mock
//! `DeviceLink` wall on loopback. Assertions are on protocol sequences, counts and final
//! states; printed rates and round trips are measurements, never asserted.

use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use haptic_bridge::hapticmaster::{self, ExitState, HapticMaster, HapticMasterParams};
use haptic_bridge::hbp::{self, status};
use haptic_bridge::serial::{EmulatorFaults, SerialDevice, SerialEmulator, SerialParams};
use haptic_bridge::sim::Script;
use haptic_bridge::{BridgeConfig, BridgeReport, HapticDevice, MonotonicClock, run};
use haptics_proto::v1::device_link_server::{DeviceLink, DeviceLinkServer};
use haptics_proto::v1::{DeviceSample, ForceCommand, Vec3};
use serialport::{SerialPort, TTYPort};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::TcpIncoming;
use tonic::{Request, Response, Status, Streaming};

/// PTY pairs are created one at a time (serialport's own tests say `pair()` is not
/// thread-safe).
static PTY: Mutex<()> = Mutex::new(());

fn press(start_m: [f64; 3], depth_m: f64, hold_s: f64) -> Script {
    Script::Press {
        start_m,
        direction: [-1.0, 0.0, 0.0],
        depth_m,
        speed_m_per_s: 0.02,
        hold_s,
    }
}

/// A virtual wall `F = k max(0, wall_x - x)` along +x answering every sample.
#[derive(Clone)]
struct Wall {
    k_n_per_m: f64,
    wall_x_m: f64,
}

#[tonic::async_trait]
impl DeviceLink for Wall {
    type ConnectStream = Pin<Box<dyn Stream<Item = Result<ForceCommand, Status>> + Send>>;

    async fn connect(
        &self,
        request: Request<Streaming<DeviceSample>>,
    ) -> Result<Response<Self::ConnectStream>, Status> {
        let mut inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(256);
        let (k, wall_x) = (self.k_n_per_m, self.wall_x_m);
        tokio::spawn(async move {
            while let Ok(Some(s)) = inbound.message().await {
                let x = s.position_m.unwrap_or_default().x;
                let pen = (wall_x - x).max(0.0);
                let mut stiffness = vec![0.0; 9];
                stiffness[0] = if pen > 0.0 { -k } else { 0.0 };
                let cmd = ForceCommand {
                    seq: s.seq,
                    force_n: Some(Vec3::new(k * pen, 0.0, 0.0)),
                    in_contact: pen > 0.0,
                    stiffness_n_per_m: stiffness,
                    ..Default::default()
                };
                if tx.send(Ok(cmd)).await.is_err() {
                    return;
                }
            }
        });
        let mut r = Response::new(Box::pin(ReceiverStream::new(rx)) as Self::ConnectStream);
        r.metadata_mut()
            .insert("haptics-max-force-n", "2".parse().unwrap());
        r.metadata_mut()
            .insert("haptics-max-force-rate-n-per-s", "300".parse().unwrap());
        Ok(r)
    }
}

async fn serve(wall: Wall) -> (String, oneshot::Sender<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (tx, rx) = oneshot::channel::<()>();
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(DeviceLinkServer::new(wall))
            .serve_with_incoming_shutdown(incoming, async {
                let _ = rx.await;
            }),
    );
    (url, tx)
}

async fn bridge(device: Box<dyn HapticDevice>, url: String, seconds: f64) -> BridgeReport {
    let spec = device.spec().clone();
    let mut config = BridgeConfig::new(url, "s", &spec);
    config.max_duration = Some(Duration::from_secs_f64(seconds));
    let (_tx, rx) = watch::channel(false);
    run(device, Arc::new(MonotonicClock::new()), config, rx)
        .await
        .unwrap()
}

fn hm_params(addr: std::net::SocketAddr) -> HapticMasterParams {
    let mut p = HapticMasterParams::new(addr);
    // The shared 2-core machine can stall a thread for tens of ms: generous for tests.
    p.io_timeout = Duration::from_millis(500);
    p.setup_timeout = Duration::from_secs(10);
    p
}

#[test]
fn hapticmaster_calibrates_renders_and_leaves_a_safe_state_on_every_exit_path() {
    let emu = hapticmaster::Emulator::spawn(
        press([0.45, 0.0, 0.0], 0.004, 0.2),
        Duration::from_millis(100),
    )
    .unwrap();
    let mut hm = HapticMaster::connect(hm_params(emu.addr())).unwrap();
    let log = emu.log();
    assert_eq!(
        log.states,
        ["init", "force"],
        "calibrates, then force state"
    );
    assert_eq!(log.effects, ["bridgeForce"]);
    let s = hm.read(0).unwrap();
    assert!((s.position_m[0] - 0.45).abs() < 1e-6, "{s:?}");
    hm.write_force([0.0, 0.0, 1.5]).unwrap();
    assert_eq!(emu.log().rendered.last().unwrap().1, [0.0, 0.0, 1.5]);
    // Output disabled: zero, effect disabled; enabled again renders the next command.
    hm.set_output_enabled(false).unwrap();
    assert_eq!(emu.log().rendered.last().unwrap().1, [0.0; 3]);
    hm.set_output_enabled(true).unwrap();
    hm.write_force([0.5, 0.0, 0.0]).unwrap();
    assert_eq!(emu.log().rendered.last().unwrap().1, [0.5, 0.0, 0.0]);
    // A non-finite force never leaves the driver.
    assert!(hm.write_force([f64::NAN, 0.0, 0.0]).is_err());
    // Exit path 1: drop without an explicit stop (an error unwinding through the bridge).
    drop(hm);
    let log = emu.log();
    assert_eq!(log.rendered.last().unwrap().1, [0.0; 3]);
    assert!(log.effects.is_empty(), "remove all on exit");
    assert_eq!(log.states.last().unwrap(), "stop");
    // Exit path 2: explicit safe_stop, exit state off; already calibrated: no init.
    let mut p = hm_params(emu.addr());
    p.exit_state = ExitState::Off;
    let mut hm = HapticMaster::connect(p).unwrap();
    hm.write_force([1.0, 0.0, 0.0]).unwrap();
    hm.safe_stop();
    hm.safe_stop(); // idempotent
    let log = emu.log();
    assert_eq!(log.states, ["init", "force", "stop", "force", "off"]);
    assert_eq!(log.rendered.last().unwrap().1, [0.0; 3]);
    assert_eq!(log.connections, 2);
}

#[test]
fn a_late_hapticmaster_reply_never_answers_the_next_command() {
    let emu = hapticmaster::Emulator::spawn(
        press([0.45, 0.0, 0.0], 0.004, 10.0),
        Duration::from_millis(10),
    )
    .unwrap();
    let mut p = hm_params(emu.addr());
    p.io_timeout = Duration::from_millis(50);
    let mut hm = HapticMaster::connect(p).unwrap();
    hm.write_force([0.0, 0.0, 0.2]).unwrap();
    emu.delay_next_reply(200);
    assert!(
        hm.read(0).is_err(),
        "the reply came after the 50 ms timeout"
    );
    // The next commands reconnect (once the emulator, which serves one connection at a time,
    // is done with the stalled one) and get their own replies: never "Effect's force set"
    // read as a position.
    let t = Instant::now();
    let s = loop {
        match hm.read(0) {
            Ok(s) => break s,
            Err(e) => {
                assert!(!e.to_string().contains("expected [x,y,z]"), "{e}");
                assert!(t.elapsed() < Duration::from_secs(5), "{e}");
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    };
    assert!((s.position_m[0] - 0.45).abs() < 1e-6, "{s:?}");
    hm.write_force([0.0, 0.0, 0.3]).unwrap();
    assert_eq!(emu.log().rendered.last().unwrap().1, [0.0, 0.0, 0.3]);
    assert!(emu.log().connections >= 2);
}

#[test]
fn hapticmaster_command_rate_against_the_emulator() {
    let emu = hapticmaster::Emulator::spawn(
        press([0.45, 0.0, 0.0], 0.004, 10.0),
        Duration::from_millis(10),
    )
    .unwrap();
    let mut hm = HapticMaster::connect(hm_params(emu.addr())).unwrap();
    let n = 2_000;
    let before = hm.commands();
    let t = Instant::now();
    for i in 0..n {
        hm.read(i).unwrap();
        hm.write_force([0.0, 0.0, 0.001 * (i % 10) as f64]).unwrap();
    }
    let dt = t.elapsed().as_secs_f64();
    let cmds = hm.commands() - before;
    // A measurement (docs/benchmarks.md), not an assertion on timing.
    println!(
        "hapticmaster emulator: {cmds} commands in {dt:.3} s = {:.0} commands/s, {:.0} device ticks/s (read + write)",
        cmds as f64 / dt,
        n as f64 / dt
    );
    assert_eq!(cmds, 2 * n);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bridge_drives_a_hapticmaster_emulator_against_a_wall() {
    let emu = hapticmaster::Emulator::spawn(
        press([0.45, 0.0, 0.0], 0.004, 0.2),
        Duration::from_millis(50),
    )
    .unwrap();
    let addr = emu.addr();
    let hm = tokio::task::spawn_blocking(move || HapticMaster::connect(hm_params(addr)))
        .await
        .unwrap()
        .unwrap();
    let (url, _stop) = serve(Wall {
        k_n_per_m: 500.0,
        wall_x_m: 0.448,
    })
    .await;
    let r = bridge(Box::new(hm), url, 1.0).await;
    let s = &r.summary;
    println!("hapticmaster via bridge: {s}");
    assert!(s.connected() && s.forces_received > 100, "{s}");
    // The scene's 2 N limit (response header) is below the device's 100 N.
    assert_eq!(s.max_force_n, 2.0);
    assert!(s.peak_force_n > 0.2 && s.peak_force_n <= 2.0, "{s}");
    let log = emu.log();
    assert!(log.rendered.iter().any(|(_, f)| f[0] > 0.2));
    assert_eq!(log.rendered.last().unwrap().1, [0.0; 3]);
    assert_eq!(log.states.last().unwrap(), "stop");
}

fn pty_pair() -> (TTYPort, TTYPort) {
    let (mut master, mut slave) = TTYPort::pair().expect("a pseudo-terminal pair");
    master.set_timeout(Duration::ZERO).unwrap();
    slave.set_timeout(Duration::ZERO).unwrap();
    (master, slave)
}

#[test]
fn serial_handshake_ticks_crc_errors_and_device_watchdog_over_a_pty() {
    let _pty = PTY
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let (master, slave) = pty_pair();
    let path = slave.name().expect("slave path");
    let emu = SerialEmulator::spawn(
        master,
        press([0.014, 0.0, -0.005], 0.004, 1.0),
        EmulatorFaults { corrupt_every: 20 },
    )
    .unwrap();
    // The driver opens the slave by path with baud 0 (a PTY refuses baud ioctls).
    let mut dev = SerialDevice::open_path(&path, 0, SerialParams::default()).unwrap();
    assert_eq!(dev.spec().name, "hbp-emulator");
    assert_eq!(dev.spec().max_force_n, 5.0);
    let clock = MonotonicClock::new();
    use haptic_bridge::Clock;
    let mut ok = 0;
    let mut next = clock.now_us();
    for i in 0..400u64 {
        if let Ok(s) = dev.read(clock.now_us()) {
            ok += 1;
            assert!((s.position_m[0] - 0.014).abs() < 0.005);
        }
        dev.write_force([0.0, 0.0, 0.001 * (i % 5) as f64]).unwrap();
        next += 1_000;
        clock.sleep_until_us(next);
    }
    assert!(ok > 300, "{ok} good reads of 400");
    let st = dev.decode_stats();
    println!("serial over PTY: {st:?}, emulator ticks {}", emu.ticks());
    // A flipped byte breaks the COBS structure or the CRC: either way the frame is dropped.
    // Every 20th of the frames the emulator sent is corrupt (it sent about 200 in the 0.4 s
    // here, fewer on a loaded machine: 190 once, so 9 corrupt ones); the last one may still
    // be in flight.
    let ticks = emu.ticks();
    assert!(ticks >= 150, "the emulator sent {ticks} frames");
    assert!(
        st.crc_errors + st.malformed + 1 >= ticks / 20,
        "the emulator corrupts every 20th STATE: {st:?} of {ticks}"
    );
    assert!(dev.status().unwrap() & status::FORCE_ENABLED != 0);
    let log = emu.log();
    assert!(log.rendered.iter().any(|(_, f)| f[2] > 0.0));
    // The host falls silent: the device watchdog (20 ms) zeroes the force by its own clock.
    dev.write_force([0.0, 0.0, 0.5]).unwrap();
    std::thread::sleep(Duration::from_millis(150));
    let log = emu.log();
    assert_eq!(log.rendered.last().unwrap().1, [0.0; 3]);
    assert!(log.watchdog_trips >= 1);
    let _ = dev.read(clock.now_us());
    assert!(dev.status().unwrap() & status::WD_TRIPPED != 0);
    // Safe stop sends a zero force with the enable flag cleared.
    dev.safe_stop();
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(emu.log().rendered.last().unwrap().1, [0.0; 3]);
    // The emulator dies: the host reports it (end of file, or no STATE for 20 ms).
    drop(emu);
    let t = Instant::now();
    let mut failed = false;
    while t.elapsed() < Duration::from_secs(2) {
        if dev.read(clock.now_us()).is_err() {
            failed = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(failed, "a dead device must be reported");
    drop(slave);
}

#[test]
fn serial_handshake_times_out_on_a_silent_port() {
    let _pty = PTY
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let (_master, slave) = pty_pair();
    let params = SerialParams {
        handshake_timeout: Duration::from_millis(100),
        ..SerialParams::default()
    };
    let e = SerialDevice::open(
        Box::new(slave) as Box<dyn SerialPort>,
        Arc::new(MonotonicClock::new()),
        params,
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("no CAPS"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bridge_drives_a_serial_arm_against_a_wall() {
    // Only creating the pair needs the lock (and a std guard must not live across an await).
    let (master, slave) = {
        let _pty = PTY
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        pty_pair()
    };
    let emu = SerialEmulator::spawn(
        master,
        press([0.014, 0.0, -0.005], 0.004, 0.2),
        EmulatorFaults::default(),
    )
    .unwrap();
    let dev = SerialDevice::open(
        Box::new(slave) as Box<dyn SerialPort>,
        Arc::new(MonotonicClock::new()),
        SerialParams::default(),
    )
    .unwrap();
    let (url, _stop) = serve(Wall {
        k_n_per_m: 500.0,
        wall_x_m: 0.012,
    })
    .await;
    let r = bridge(Box::new(dev), url, 1.0).await;
    let s = &r.summary;
    println!("serial via bridge: {s}");
    assert!(s.connected() && s.forces_received > 100, "{s}");
    assert!(s.peak_force_n > 0.2, "{s}");
    let log = emu.stop();
    assert!(log.rendered.iter().any(|(_, f)| f[0] > 0.2));
    assert_eq!(log.rendered.last().unwrap().1, [0.0; 3]);
    assert_eq!(log.crc_errors_in, 0);
    let _ = hbp::VERSION;
}
