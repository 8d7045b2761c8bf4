//! The `openhaptics` driver: Phantom / Touch devices through the vendor's HDAPI (OpenHaptics,
//! `libHD.so`), loaded at run time (devices.md section 1.2; \[S8\] `hdDefines.h`, \[S10\]
//! HelloHapticDevice, \[S11\] PreventWarmMotors).
//!
//! The driver is written against [`HdApi`], the table of the HDAPI entry points it calls
//! ([`HdTable`]) together with the library they live in. With the cargo feature `openhaptics`
//! (off by default: the library is closed and absent in CI), `HdApi::load` fills the table
//! from `libHD.so` with `libloading` and a missing library or symbol is a clear error naming
//! it. Without the feature the driver logic still compiles and is unit-tested against a fake
//! table (a simulated device and scheduler in this module's tests), wrapped by the `unsafe`
//! [`HdApi::from_table`].
//!
//! Soundness: an [`HdApi`] owns (shares) the library its pointers came from, its fields are
//! private and it is `Clone`, not `Copy`; the device keeps it in the servo state the callback
//! reads, so the library stays mapped until the callback is unscheduled. Safe code cannot
//! drop the library under a live table, nor build a table of arbitrary pointers:
//!
//! ```compile_fail
//! use haptic_bridge::openhaptics::{HdApi, HdTable};
//! fn forge(table: HdTable) -> HdApi {
//!     HdApi { table } // private fields: only `load` and the unsafe `from_table` make one
//! }
//! ```
//!
//! ```compile_fail,E0133
//! use haptic_bridge::openhaptics::{HdApi, HdTable};
//! fn forge(table: HdTable) -> HdApi {
//!     HdApi::from_table(table) // E0133: calling an unsafe function needs an unsafe block
//! }
//! ```
//!
//! ```
//! use haptic_bridge::openhaptics::{HdApi, HdTable};
//! fn forge(table: HdTable) -> HdApi {
//!     // SAFETY: the caller of `forge` vouches for the table (the same code as above, with
//!     // the unsafe block: it compiles, so the failures above are the ones the docs name).
//!     unsafe { HdApi::from_table(table) }
//! }
//! ```
//!
//! How it runs: `hdInitDevice(HD_DEFAULT_DEVICE)`; the limits are read from the device
//! (`HD_NOMINAL_MAX_FORCE`, `HD_NOMINAL_MAX_CONTINUOUS_FORCE`, `HD_NOMINAL_MAX_STIFFNESS` and
//! `HD_NOMINAL_MAX_DAMPING` in N/mm and N/(mm/s), `HD_USABLE_WORKSPACE_DIMENSIONS` in mm);
//! `hdEnable(HD_FORCE_OUTPUT)`; a servo callback is scheduled with
//! `hdScheduleAsynchronous(.., HD_MAX_SCHEDULER_PRIORITY)` and `hdStartScheduler()` runs it at
//! the device's 1 kHz. Each callback: `hdBeginFrame`, read position and velocity (mm, mm/s),
//! the safety switch where the device has one (`HD_CURRENT_SAFETY_SWITCH`), write the force the
//! bridge last commanded (N) or zero when the output is disabled, the switch is released, or the
//! bridge has not written for 20 ms (a driver-side watchdog, devices.md S2), `hdEndFrame`, then
//! check `hdGetError`. The bridge's device thread meets the callback in a small slot under a
//! mutex that the callback only `try_lock`s (it never waits on the bridge).
//!
//! Units: mm -> m and mm/s -> m/s on the way in, N both ways; the frame is OpenHaptics' (x
//! right, y up, z toward the user), already right-handed: [`crate::transform`] maps it to the
//! scene. The force clamp is the peak force (`HD_NOMINAL_MAX_FORCE`, 3.3 N on a Touch), lowered
//! by the guard's thermal limit (S8, [`crate::thermal`]) toward the continuous force
//! (`HD_NOMINAL_MAX_CONTINUOUS_FORCE`, 0.88 N) while the RMS force says the motors run hot.
//!
//! Neighbours: implements [`crate::device::HapticDevice`].

use std::ffi::{c_char, c_int, c_uint, c_ulong, c_ushort, c_void};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, vec3};

/// HDAPI constants used by the driver (values from `hdDefines.h`, OpenHaptics 3.x).
pub mod hd {
    /// `HD_SUCCESS`.
    pub const SUCCESS: u32 = 0x0000;
    /// `HD_CURRENT_SAFETY_SWITCH`.
    pub const CURRENT_SAFETY_SWITCH: u32 = 0x2001;
    /// `HD_CURRENT_POSITION` (mm).
    pub const CURRENT_POSITION: u32 = 0x2050;
    /// `HD_CURRENT_VELOCITY` (mm/s).
    pub const CURRENT_VELOCITY: u32 = 0x2051;
    /// `HD_USABLE_WORKSPACE_DIMENSIONS` (mm: min x, y, z, max x, y, z).
    pub const USABLE_WORKSPACE_DIMENSIONS: u32 = 0x2551;
    /// `HD_NOMINAL_MAX_STIFFNESS` (N/mm).
    pub const NOMINAL_MAX_STIFFNESS: u32 = 0x2602;
    /// `HD_NOMINAL_MAX_FORCE` (N).
    pub const NOMINAL_MAX_FORCE: u32 = 0x2603;
    /// `HD_NOMINAL_MAX_CONTINUOUS_FORCE` (N).
    pub const NOMINAL_MAX_CONTINUOUS_FORCE: u32 = 0x2604;
    /// `HD_NOMINAL_MAX_DAMPING` (N/(mm/s)).
    pub const NOMINAL_MAX_DAMPING: u32 = 0x2609;
    /// `HD_CURRENT_FORCE` (N).
    pub const CURRENT_FORCE: u32 = 0x2700;
    /// `HD_FORCE_OUTPUT`.
    pub const FORCE_OUTPUT: u32 = 0x4000;
    /// `HD_MAX_SCHEDULER_PRIORITY` (`USHRT_MAX`).
    pub const MAX_SCHEDULER_PRIORITY: u16 = u16::MAX;
    /// `HD_CALLBACK_DONE`.
    pub const CALLBACK_DONE: u32 = 0;
    /// `HD_CALLBACK_CONTINUE`.
    pub const CALLBACK_CONTINUE: u32 = 1;
    /// `HD_INVALID_HANDLE`.
    pub const INVALID_HANDLE: u32 = 0xFFFF_FFFF;
}

/// `HDErrorInfo` as returned by `hdGetError`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HdErrorInfo {
    /// The `HD_` error code (`HD_SUCCESS` when none).
    pub error_code: c_uint,
    /// The device's internal error code.
    pub internal_error_code: c_int,
    /// The device handle current when it happened.
    pub hhd: c_uint,
}

/// `HDSchedulerCallback`.
pub type HdCallback = unsafe extern "C" fn(*mut c_void) -> c_uint;

/// The HDAPI entry points the driver calls (C calling convention, as `hdDefines.h` declares
/// them on Linux). Filled by `HdApi::load` from `libHD.so`, or by a fake in tests; calling
/// through a field is `unsafe`, and the driver only does so through an [`HdApi`].
#[derive(Clone, Copy)]
pub struct HdTable {
    /// `HHD hdInitDevice(HDstring)`.
    pub init_device: unsafe extern "C" fn(*const c_char) -> c_uint,
    /// `void hdDisableDevice(HHD)`.
    pub disable_device: unsafe extern "C" fn(c_uint),
    /// `HDErrorInfo hdGetError(void)`.
    pub get_error: unsafe extern "C" fn() -> HdErrorInfo,
    /// `void hdEnable(HDenum)`.
    pub enable: unsafe extern "C" fn(c_uint),
    /// `void hdDisable(HDenum)`.
    pub disable: unsafe extern "C" fn(c_uint),
    /// `void hdStartScheduler(void)`.
    pub start_scheduler: unsafe extern "C" fn(),
    /// `void hdStopScheduler(void)`.
    pub stop_scheduler: unsafe extern "C" fn(),
    /// `HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback, void*, HDushort)`.
    pub schedule_asynchronous: unsafe extern "C" fn(HdCallback, *mut c_void, c_ushort) -> c_ulong,
    /// `void hdUnschedule(HDSchedulerHandle)`.
    pub unschedule: unsafe extern "C" fn(c_ulong),
    /// `void hdBeginFrame(HHD)`.
    pub begin_frame: unsafe extern "C" fn(c_uint),
    /// `void hdEndFrame(HHD)`.
    pub end_frame: unsafe extern "C" fn(c_uint),
    /// `void hdGetDoublev(HDenum, HDdouble*)`.
    pub get_doublev: unsafe extern "C" fn(c_uint, *mut f64),
    /// `void hdSetDoublev(HDenum, const HDdouble*)`.
    pub set_doublev: unsafe extern "C" fn(c_uint, *const f64),
    /// `void hdGetBooleanv(HDenum, HDboolean*)`.
    pub get_booleanv: unsafe extern "C" fn(c_uint, *mut u8),
}

/// The HDAPI table and the library its entry points live in (module documentation,
/// "Soundness"). Made by `HdApi::load` (feature `openhaptics`) or, for a table of one's own
/// (a fake device), by the `unsafe` [`HdApi::from_table`]; clones share the library, which is
/// unloaded when the last clone is dropped.
#[derive(Clone)]
pub struct HdApi {
    table: HdTable,
    /// Keeps the vendor library mapped while any clone (the device's servo state) lives.
    #[cfg(feature = "openhaptics")]
    _library: Option<Arc<libloading::Library>>,
}

impl std::fmt::Debug for HdApi {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("HdApi { .. }")
    }
}

impl HdApi {
    /// Wraps a table whose entry points are not from a library this type loaded (the fake
    /// HDAPI of the tests).
    ///
    /// # Safety
    /// Every pointer in `table` must behave as the HDAPI prototype its field documents
    /// (`hd.h`, OpenHaptics 3.x: out-pointers written within the parameter's size, the
    /// scheduler calling the callback only with the data it was given, until
    /// `hdStopScheduler`/`hdUnschedule` return) and stay callable while any clone of the
    /// returned value lives.
    pub unsafe fn from_table(table: HdTable) -> Self {
        Self {
            table,
            #[cfg(feature = "openhaptics")]
            _library: None,
        }
    }

    /// Loads `libHD.so` (or `path`) and fills the table; the result owns the library.
    ///
    /// # Errors
    /// [`DeviceError::Comm`] naming the library that could not be loaded (and how to install
    /// it) or the symbol that is missing.
    #[cfg(feature = "openhaptics")]
    pub fn load(path: Option<&std::path::Path>) -> Result<Self, DeviceError> {
        let names: Vec<std::ffi::OsString> = match path {
            Some(p) => vec![p.as_os_str().to_owned()],
            None => LIBRARY_NAMES.iter().map(Into::into).collect(),
        };
        let mut last = String::new();
        for name in &names {
            // SAFETY: loading the vendor library runs its initialisers; this is the documented
            // way to use OpenHaptics, and nothing else of ours runs concurrently with it here.
            match unsafe { libloading::Library::new(name) } {
                Ok(lib) => {
                    let table = table(&lib)?;
                    return Ok(Self {
                        table,
                        _library: Some(Arc::new(lib)),
                    });
                }
                Err(e) => last = format!("{}: {e}", name.to_string_lossy()),
            }
        }
        Err(DeviceError::Comm(format!(
            "OpenHaptics: cannot load the HDAPI library ({last}); install 3D Systems OpenHaptics \
             for Linux and the Touch device driver, or pass --hd-library PATH"
        )))
    }
}

/// The library names tried by `HdApi::load` when no path is given.
pub const LIBRARY_NAMES: [&str; 2] = ["libHD.so", "libHD.so.3.4"];

#[cfg(feature = "openhaptics")]
fn table(lib: &libloading::Library) -> Result<HdTable, DeviceError> {
    fn sym<T: Copy>(lib: &libloading::Library, name: &str) -> Result<T, DeviceError> {
        // SAFETY: the symbol's type is the HDAPI prototype from hdDefines.h/hd.h that the
        // field it fills declares; the library outlives the table (`HdApi::load` stores both).
        unsafe {
            lib.get::<T>(name.as_bytes())
                .map(|s| *s)
                .map_err(|e| DeviceError::Comm(format!("OpenHaptics: symbol {name} missing: {e}")))
        }
    }
    Ok(HdTable {
        init_device: sym(lib, "hdInitDevice")?,
        disable_device: sym(lib, "hdDisableDevice")?,
        get_error: sym(lib, "hdGetError")?,
        enable: sym(lib, "hdEnable")?,
        disable: sym(lib, "hdDisable")?,
        start_scheduler: sym(lib, "hdStartScheduler")?,
        stop_scheduler: sym(lib, "hdStopScheduler")?,
        schedule_asynchronous: sym(lib, "hdScheduleAsynchronous")?,
        unschedule: sym(lib, "hdUnschedule")?,
        begin_frame: sym(lib, "hdBeginFrame")?,
        end_frame: sym(lib, "hdEndFrame")?,
        get_doublev: sym(lib, "hdGetDoublev")?,
        set_doublev: sym(lib, "hdSetDoublev")?,
        get_booleanv: sym(lib, "hdGetBooleanv")?,
    })
}

/// The bridge writing nothing for this long zeroes the force in the servo callback.
pub const CALLBACK_WATCHDOG: Duration = Duration::from_millis(20);

/// The slot between the bridge's device thread and the servo callback.
#[derive(Debug, Clone, Copy)]
struct Slot {
    position_mm: [f64; 3],
    velocity_mm_s: [f64; 3],
    safety_switch: bool,
    force_n: [f64; 3],
    force_written: Option<Instant>,
    enabled: bool,
    /// A device error code from the callback (`HD_SUCCESS` when none).
    error: u32,
    frames: u64,
    stop: bool,
}

struct Servo {
    api: HdApi,
    hhd: c_uint,
    has_safety_switch: bool,
    slot: Mutex<Slot>,
}

/// The servo callback: one HDAPI frame. Never blocks on the bridge (`try_lock`).
unsafe extern "C" fn servo_callback(data: *mut c_void) -> c_uint {
    // SAFETY: `data` is the `Arc<Servo>` pointer `OpenHapticsDevice::open` passed to
    // `hdScheduleAsynchronous`; it stays alive until after the callback is unscheduled and the
    // scheduler stopped (`safe_stop`).
    let servo = unsafe { &*(data as *const Servo) };
    let api = &servo.api.table;
    let (mut p, mut v) = ([0.0f64; 3], [0.0f64; 3]);
    let mut switch = 1u8;
    // SAFETY: HDAPI calls inside a scheduler callback with valid out-pointers of the sizes the
    // parameters need (3 doubles, 1 boolean).
    let err = unsafe {
        (api.begin_frame)(servo.hhd);
        (api.get_doublev)(hd::CURRENT_POSITION, p.as_mut_ptr());
        (api.get_doublev)(hd::CURRENT_VELOCITY, v.as_mut_ptr());
        if servo.has_safety_switch {
            (api.get_booleanv)(hd::CURRENT_SAFETY_SWITCH, &mut switch);
        }
        (api.get_error)()
    };
    let mut force = [0.0f64; 3];
    let mut stop = false;
    if let Ok(mut s) = servo.slot.try_lock() {
        s.position_mm = p;
        s.velocity_mm_s = v;
        s.safety_switch = switch != 0;
        s.frames += 1;
        if err.error_code != hd::SUCCESS {
            s.error = err.error_code;
        }
        let fresh = s
            .force_written
            .is_some_and(|t| t.elapsed() <= CALLBACK_WATCHDOG);
        if s.enabled && s.safety_switch && fresh && vec3::is_finite(s.force_n) {
            force = s.force_n;
        }
        stop = s.stop;
    }
    // SAFETY: as above; `force` holds 3 doubles.
    unsafe {
        (api.set_doublev)(hd::CURRENT_FORCE, force.as_ptr());
        (api.end_frame)(servo.hhd);
    }
    if stop {
        hd::CALLBACK_DONE
    } else {
        hd::CALLBACK_CONTINUE
    }
}

/// A Phantom / Touch through HDAPI (module documentation).
pub struct OpenHapticsDevice {
    servo: Option<Arc<Servo>>,
    /// Raw `Arc<Servo>` handed to the scheduler; reclaimed in `safe_stop`.
    callback_data: *const Servo,
    handle: c_ulong,
    spec: DeviceSpec,
    peak_force_n: f64,
    stopped: bool,
}

// SAFETY: `callback_data` is only an owning pointer to an `Arc<Servo>` (Servo is Send + Sync:
// function pointers and a Mutex); it is never dereferenced by this type except to reclaim it.
unsafe impl Send for OpenHapticsDevice {}

fn check(api: &HdTable, what: &str) -> Result<(), DeviceError> {
    // SAFETY: plain HDAPI call.
    let e = unsafe { (api.get_error)() };
    if e.error_code == hd::SUCCESS {
        Ok(())
    } else {
        Err(DeviceError::Comm(format!(
            "OpenHaptics {what}: HD error 0x{:04X} (internal {})",
            e.error_code, e.internal_error_code
        )))
    }
}

/// The device's limits and workspace (HDAPI units converted to SI) and whether it has a
/// safety switch, read from an initialised device.
///
/// # Errors
/// [`DeviceError::Comm`] when HDAPI reports an error reading the limits; the checks of
/// [`DeviceSpec::validate`] for limits that are not finite and positive.
fn read_spec(api: &HdTable) -> Result<(DeviceSpec, bool), DeviceError> {
    let get1 = |p: u32| {
        let mut v = 0.0f64;
        // SAFETY: a scalar parameter, one double.
        unsafe { (api.get_doublev)(p, &mut v) };
        v
    };
    let peak = get1(hd::NOMINAL_MAX_FORCE);
    let continuous = get1(hd::NOMINAL_MAX_CONTINUOUS_FORCE);
    let k_n_per_mm = get1(hd::NOMINAL_MAX_STIFFNESS);
    let b_n_per_mm_s = get1(hd::NOMINAL_MAX_DAMPING);
    let mut ws = [0.0f64; 6];
    // SAFETY: six doubles.
    unsafe { (api.get_doublev)(hd::USABLE_WORKSPACE_DIMENSIONS, ws.as_mut_ptr()) };
    check(api, "reading the device limits")?;
    let mut switch = 0u8;
    // SAFETY: one boolean; devices without the switch report an error, cleared below.
    unsafe { (api.get_booleanv)(hd::CURRENT_SAFETY_SWITCH, &mut switch) };
    let has_safety_switch = check(api, "safety switch").is_ok();
    let spec = DeviceSpec {
        name: "openhaptics".into(),
        // The Touch, Desktop and Premium 1.5 (HD_INPUT_DOF / HD_OUTPUT_DOF not queried:
        // the servo renders a 3-DOF force either way).
        sensed_degrees_of_freedom: 6,
        actuated_degrees_of_freedom: 3,
        // The peak, held only as long as the thermal limit (S8) allows, toward the
        // continuous rating.
        max_force_n: peak,
        max_continuous_force_n: if continuous > 0.0 { continuous } else { peak },
        max_stiffness_n_per_m: k_n_per_mm * 1e3,
        workspace_min_m: [ws[0] * 1e-3, ws[1] * 1e-3, ws[2] * 1e-3],
        workspace_max_m: [ws[3] * 1e-3, ws[4] * 1e-3, ws[5] * 1e-3],
        rate_hz: 1000.0,
        max_damping_n_s_per_m: b_n_per_mm_s * 1e3,
    };
    spec.validate()?;
    Ok((spec, has_safety_switch))
}

impl OpenHapticsDevice {
    /// Initialises the default device through `hd_api`, reads its limits, enables force output
    /// and starts the servo callback. The device keeps `hd_api` (and so its library) in the
    /// servo state until the callback is unscheduled ([`HapticDevice::safe_stop`]).
    ///
    /// # Errors
    /// [`DeviceError::Comm`] with the HD error code of the step that failed;
    /// [`DeviceError::InvalidSpec`] for limits the device reports that are not usable. After
    /// `hdInitDevice` succeeded, every error disables the device again (`hdDisableDevice`).
    pub fn open(hd_api: HdApi) -> Result<Self, DeviceError> {
        let api = hd_api.table;
        // SAFETY: HDAPI set-up calls with valid arguments (a null config name selects the
        // default device; out-pointers sized for each parameter).
        let hhd = unsafe { (api.init_device)(std::ptr::null()) };
        if hhd == hd::INVALID_HANDLE {
            check(&api, "hdInitDevice")?;
            return Err(DeviceError::Comm(
                "OpenHaptics hdInitDevice returned an invalid handle".into(),
            ));
        }
        check(&api, "hdInitDevice")?;
        // From here on the device is initialised: an error disables it again.
        let (spec, has_safety_switch) = match read_spec(&api) {
            Ok(v) => v,
            Err(e) => {
                // SAFETY: the handle hdInitDevice returned; nothing is scheduled yet.
                unsafe { (api.disable_device)(hhd) };
                return Err(e);
            }
        };
        let peak = spec.max_force_n;
        let servo = Arc::new(Servo {
            api: hd_api,
            hhd,
            has_safety_switch,
            slot: Mutex::new(Slot {
                position_mm: [0.0; 3],
                velocity_mm_s: [0.0; 3],
                safety_switch: !has_safety_switch,
                force_n: [0.0; 3],
                force_written: None,
                enabled: true,
                error: hd::SUCCESS,
                frames: 0,
                stop: false,
            }),
        });
        let data = Arc::into_raw(servo.clone());
        // SAFETY: the callback and its data stay valid until `safe_stop` unschedules it.
        let handle = unsafe {
            (api.enable)(hd::FORCE_OUTPUT);
            let h = (api.schedule_asynchronous)(
                servo_callback,
                data as *mut c_void,
                hd::MAX_SCHEDULER_PRIORITY,
            );
            (api.start_scheduler)();
            h
        };
        let mut dev = Self {
            servo: Some(servo),
            callback_data: data,
            handle,
            spec,
            peak_force_n: peak,
            stopped: false,
        };
        if let Err(e) = check(&api, "starting the scheduler") {
            dev.safe_stop();
            return Err(e);
        }
        Ok(dev)
    }

    /// The device's peak force, N (the clamp is the continuous force; module documentation).
    pub fn peak_force_n(&self) -> f64 {
        self.peak_force_n
    }

    fn slot(&self) -> Option<std::sync::MutexGuard<'_, Slot>> {
        self.servo
            .as_ref()
            .map(|s| s.slot.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

impl HapticDevice for OpenHapticsDevice {
    fn spec(&self) -> &DeviceSpec {
        &self.spec
    }

    fn read(&mut self, now_us: u64) -> Result<DeviceState, DeviceError> {
        let s = *self
            .slot()
            .ok_or_else(|| DeviceError::Comm("OpenHaptics device stopped".into()))?;
        if s.error != hd::SUCCESS {
            return Err(DeviceError::Comm(format!(
                "OpenHaptics servo: HD error 0x{:04X}",
                s.error
            )));
        }
        if s.frames == 0 {
            return Err(DeviceError::Comm(
                "OpenHaptics: the servo callback has not run yet".into(),
            ));
        }
        Ok(DeviceState {
            time_us: now_us,
            position_m: vec3::scale(s.position_mm, 1e-3),
            velocity_m_per_s: vec3::scale(s.velocity_mm_s, 1e-3),
            motor_temperature: None,
        })
    }

    fn write_force(&mut self, force_n: [f64; 3]) -> Result<(), DeviceError> {
        if !vec3::is_finite(force_n) {
            return Err(DeviceError::NonFiniteForce(force_n));
        }
        let mut s = self
            .slot()
            .ok_or_else(|| DeviceError::Comm("OpenHaptics device stopped".into()))?;
        s.force_n = force_n;
        s.force_written = Some(Instant::now());
        Ok(())
    }

    fn finished(&self, _now_us: u64) -> bool {
        false
    }

    fn set_output_enabled(&mut self, on: bool) -> Result<(), DeviceError> {
        if let Some(mut s) = self.slot() {
            s.enabled = on;
        }
        Ok(())
    }

    fn safe_stop(&mut self) {
        if self.stopped {
            return;
        }
        self.stopped = true;
        let Some(servo) = self.servo.take() else {
            return;
        };
        {
            let mut s = servo.slot.lock().unwrap_or_else(PoisonError::into_inner);
            s.enabled = false;
            s.force_n = [0.0; 3];
        }
        // Let one callback render zero, then stop it.
        std::thread::sleep(Duration::from_millis(3));
        let api = &servo.api.table;
        // SAFETY: HDAPI shut-down sequence; after `hdStopScheduler` and `hdUnschedule` the
        // callback no longer runs, so its data can be released.
        unsafe {
            (api.stop_scheduler)();
            (api.unschedule)(self.handle);
            (api.disable)(hd::FORCE_OUTPUT);
            (api.disable_device)(servo.hhd);
            drop(Arc::from_raw(self.callback_data));
        }
    }
}

impl Drop for OpenHapticsDevice {
    fn drop(&mut self) {
        self.safe_stop();
    }
}

#[cfg(test)]
mod tests {
    //! A fake HDAPI: a simulated Touch (3.3 N peak, 0.88 N continuous, 0.5 N/mm, a +-80 mm
    //! box) and a scheduler thread calling the callback every millisecond.
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    #[derive(Default)]
    struct Fake {
        position_mm: [f64; 3],
        safety: u8,
        has_switch: bool,
        force_n: [f64; 3],
        forces_set: u64,
        output_enabled: bool,
        device_enabled: bool,
        callback: Option<(HdCallback, usize)>,
        error: u32,
        scheduler: Option<std::thread::JoinHandle<()>>,
        unscheduled: bool,
        /// An HD error code the workspace read reports (0: none).
        limits_error: u32,
        /// The workspace the device reports, mm (`None`: a Touch's +-80 x 60 x 35 mm box).
        workspace_mm: Option<[f64; 6]>,
    }

    static FAKE: Mutex<Option<Fake>> = Mutex::new(None);
    static RUNNING: AtomicBool = AtomicBool::new(false);
    /// The fake is process-global: tests take turns.
    static TURN: Mutex<()> = Mutex::new(());

    fn with<R>(f: impl FnOnce(&mut Fake) -> R) -> R {
        let mut g = FAKE.lock().unwrap_or_else(PoisonError::into_inner);
        f(g.get_or_insert_with(Fake::default))
    }

    unsafe extern "C" fn init_device(_: *const c_char) -> c_uint {
        with(|f| f.device_enabled = true);
        1
    }
    unsafe extern "C" fn disable_device(_: c_uint) {
        with(|f| f.device_enabled = false);
    }
    unsafe extern "C" fn get_error() -> HdErrorInfo {
        let code = with(|f| std::mem::take(&mut f.error));
        HdErrorInfo {
            error_code: code,
            internal_error_code: 0,
            hhd: 1,
        }
    }
    unsafe extern "C" fn enable(p: c_uint) {
        if p == hd::FORCE_OUTPUT {
            with(|f| f.output_enabled = true);
        }
    }
    unsafe extern "C" fn disable(p: c_uint) {
        if p == hd::FORCE_OUTPUT {
            with(|f| f.output_enabled = false);
        }
    }
    unsafe extern "C" fn start_scheduler() {
        let (cb, data) = with(|f| f.callback).expect("scheduled");
        RUNNING.store(true, Ordering::Release);
        let t = std::thread::spawn(move || {
            while RUNNING.load(Ordering::Acquire) {
                // SAFETY: the driver's callback with the data it registered.
                if unsafe { cb(data as *mut c_void) } == hd::CALLBACK_DONE {
                    break;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
        });
        with(|f| f.scheduler = Some(t));
    }
    unsafe extern "C" fn stop_scheduler() {
        RUNNING.store(false, Ordering::Release);
        if let Some(t) = with(|f| f.scheduler.take()) {
            let _ = t.join();
        }
    }
    unsafe extern "C" fn schedule_asynchronous(
        cb: HdCallback,
        d: *mut c_void,
        _: c_ushort,
    ) -> c_ulong {
        with(|f| f.callback = Some((cb, d as usize)));
        7
    }
    unsafe extern "C" fn unschedule(h: c_ulong) {
        assert_eq!(h, 7);
        with(|f| f.unscheduled = true);
    }
    unsafe extern "C" fn begin_frame(_: c_uint) {}
    unsafe extern "C" fn end_frame(_: c_uint) {}
    unsafe extern "C" fn get_doublev(p: c_uint, out: *mut f64) {
        let vals: Vec<f64> = match p {
            hd::NOMINAL_MAX_FORCE => vec![3.3],
            hd::NOMINAL_MAX_CONTINUOUS_FORCE => vec![0.88],
            hd::NOMINAL_MAX_STIFFNESS => vec![0.5],
            hd::NOMINAL_MAX_DAMPING => vec![0.002],
            hd::USABLE_WORKSPACE_DIMENSIONS => with(|f| {
                if f.limits_error != 0 {
                    f.error = f.limits_error;
                }
                f.workspace_mm
                    .unwrap_or([-80.0, -60.0, -35.0, 80.0, 60.0, 35.0])
                    .to_vec()
            }),
            hd::CURRENT_POSITION => with(|f| f.position_mm.to_vec()),
            hd::CURRENT_VELOCITY => vec![10.0, 0.0, 0.0],
            _ => vec![0.0],
        };
        for (i, v) in vals.into_iter().enumerate() {
            // SAFETY: the caller passes room for the parameter's size.
            unsafe { *out.add(i) = v };
        }
    }
    unsafe extern "C" fn set_doublev(p: c_uint, v: *const f64) {
        if p == hd::CURRENT_FORCE {
            // SAFETY: three doubles.
            let f = unsafe { [*v, *v.add(1), *v.add(2)] };
            with(|x| {
                x.force_n = f;
                x.forces_set += 1;
            });
        }
    }
    unsafe extern "C" fn get_booleanv(p: c_uint, out: *mut u8) {
        if p == hd::CURRENT_SAFETY_SWITCH {
            with(|f| {
                if f.has_switch {
                    // SAFETY: one boolean.
                    unsafe { *out = f.safety };
                } else {
                    f.error = 0x0100; // HD_INVALID_ENUM: no such switch on this device
                }
            });
        }
    }

    fn fake_api() -> HdApi {
        let table = HdTable {
            init_device,
            disable_device,
            get_error,
            enable,
            disable,
            start_scheduler,
            stop_scheduler,
            schedule_asynchronous,
            unschedule,
            begin_frame,
            end_frame,
            get_doublev,
            set_doublev,
            get_booleanv,
        };
        // SAFETY: the fake's functions follow the HDAPI prototypes (out-pointers written within
        // each parameter's size, the scheduler thread joined by `stop_scheduler`) and are
        // statics, callable for the whole process.
        unsafe { HdApi::from_table(table) }
    }

    fn device_force() -> [f64; 3] {
        with(|f| f.force_n)
    }

    /// Polls `cond` for up to 2 s (the fake scheduler runs on the shared machine's clock).
    fn eventually(mut cond: impl FnMut() -> bool) -> bool {
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(2) {
            if cond() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        false
    }

    #[test]
    fn limits_units_forces_watchdog_and_shutdown() {
        let _turn = TURN.lock().unwrap_or_else(PoisonError::into_inner);
        *FAKE.lock().unwrap() = Some(Fake {
            position_mm: [10.0, -20.0, 5.0],
            ..Fake::default()
        });
        let mut d = OpenHapticsDevice::open(fake_api()).unwrap();
        let s = d.spec().clone();
        // Limits read from the device: the peak as clamp, the continuous force for the thermal
        // limit (S8), N/mm -> N/m, mm -> m.
        assert_eq!(s.max_force_n, 3.3);
        assert_eq!(s.max_continuous_force_n, 0.88);
        assert_eq!(d.peak_force_n(), 3.3);
        assert!((s.max_stiffness_n_per_m - 500.0).abs() < 1e-9);
        assert!((s.max_damping_n_s_per_m - 2.0).abs() < 1e-9);
        assert!((s.workspace_min_m[0] + 0.08).abs() < 1e-12);
        assert!((s.workspace_max_m[2] - 0.035).abs() < 1e-12);
        assert!(with(|f| f.output_enabled));
        // Position in metres once the callback has run.
        assert!(eventually(|| d.read(0).is_ok()));
        let st = d.read(0).unwrap();
        assert!(vec3::norm(vec3::sub(st.position_m, [0.01, -0.02, 0.005])) < 1e-12);
        assert!((st.velocity_m_per_s[0] - 0.01).abs() < 1e-12);
        // A written force reaches the device ...
        d.write_force([0.1, 0.2, -0.3]).unwrap();
        assert!(eventually(|| device_force() == [0.1, 0.2, -0.3]));
        // ... and goes to zero when the bridge stops writing for 20 ms.
        assert!(eventually(|| device_force() == [0.0; 3]));
        // Disabled output: zero even while writing.
        d.set_output_enabled(false).unwrap();
        d.write_force([0.5, 0.0, 0.0]).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(device_force(), [0.0; 3]);
        // Every exit path: zero, scheduler stopped, output and device disabled.
        d.set_output_enabled(true).unwrap();
        d.write_force([0.5, 0.0, 0.0]).unwrap();
        assert!(eventually(|| device_force() == [0.5, 0.0, 0.0]));
        drop(d);
        assert_eq!(device_force(), [0.0; 3]);
        with(|f| {
            assert!(f.unscheduled && !f.output_enabled && !f.device_enabled);
            assert!(f.scheduler.is_none());
        });
    }

    #[test]
    fn a_failed_open_disables_the_device_again() {
        let _turn = TURN.lock().unwrap_or_else(PoisonError::into_inner);
        let cases = [
            (
                Fake {
                    limits_error: 0x0200,
                    ..Fake::default()
                },
                "reading the device limits: HD error 0x0200",
            ),
            (
                Fake {
                    workspace_mm: Some([80.0, -60.0, -35.0, -80.0, 60.0, 35.0]),
                    ..Fake::default()
                },
                "workspace axis 0",
            ),
        ];
        for (fake, expected) in cases {
            *FAKE.lock().unwrap() = Some(fake);
            let Err(e) = OpenHapticsDevice::open(fake_api()) else {
                panic!("open succeeded on a device that reports {expected}");
            };
            assert!(e.to_string().contains(expected), "{e}");
            with(|f| {
                assert!(!f.device_enabled, "the device stays enabled after: {e}");
                assert!(!f.output_enabled && f.callback.is_none());
            });
        }
    }

    #[test]
    fn the_safety_switch_is_honoured() {
        let _turn = TURN.lock().unwrap_or_else(PoisonError::into_inner);
        *FAKE.lock().unwrap() = Some(Fake {
            has_switch: true,
            safety: 0,
            ..Fake::default()
        });
        let mut d = OpenHapticsDevice::open(fake_api()).unwrap();
        assert!(eventually(|| d.read(0).is_ok()));
        let before = with(|f| f.forces_set);
        for _ in 0..10 {
            d.write_force([0.3, 0.0, 0.0]).unwrap();
            std::thread::sleep(Duration::from_millis(1));
        }
        assert!(eventually(|| with(|f| f.forces_set) > before + 3));
        assert_eq!(device_force(), [0.0; 3], "switch released: no force");
        with(|f| f.safety = 1);
        assert!(eventually(|| {
            d.write_force([0.3, 0.0, 0.0]).unwrap();
            device_force() == [0.3, 0.0, 0.0]
        }));
        d.safe_stop();
        assert_eq!(device_force(), [0.0; 3]);
    }

    #[cfg(feature = "openhaptics")]
    #[test]
    fn a_missing_library_is_named() {
        let e = HdApi::load(Some(std::path::Path::new("/nonexistent/libHD.so")))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("/nonexistent/libHD.so") && e.contains("OpenHaptics"),
            "{e}"
        );
    }
}
