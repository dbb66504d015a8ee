//! `dioptra doctor [--config rig.toml]`: whether this machine can run the rig, one line per
//! check, each `ok`, `note`, `warn` or `FAIL`, and under each that is not ok the command that
//! fixes it. Checks: the GPU adapters and their drivers, the udev rules installed against
//! `dioptra udev`, and with a config each configured device (present, readable and writable
//! by this user; simulated ones say so) and the API's address (free to bind). Exit 1 when a
//! check failed.

use std::path::{Path, PathBuf};

use dioptra_rig::config::{Listen, Port, RenderBackend, RigConfig, SinkKind};
use dioptra_transport::discovery::{self, Discovery, FoundDevice, Interface};

#[derive(clap::Args)]
pub struct Args {
    /// The rig config whose devices and API address to check (without it: the GPU and the
    /// udev rules only).
    #[arg(long)]
    config: Option<PathBuf>,
    /// The installed udev rules, compared with what `dioptra udev` prints.
    #[arg(
        long,
        value_name = "FILE",
        default_value = "/etc/udev/rules.d/70-dioptra.rules"
    )]
    udev_rules: PathBuf,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    Ok,
    /// Worth knowing, nothing to fix.
    Note,
    /// Runs, but not as a rig should (a software GPU, seat-only device access).
    Warn,
    Fail,
}

/// One check's line, and the command that fixes what it found.
#[derive(Debug)]
struct Check {
    verdict: Verdict,
    topic: String,
    what: String,
    fix: Option<String>,
}

impl Check {
    fn new(verdict: Verdict, topic: impl Into<String>, what: impl Into<String>) -> Check {
        Check {
            verdict,
            topic: topic.into(),
            what: what.into(),
            fix: None,
        }
    }
    fn fix(mut self, fix: impl Into<String>) -> Check {
        self.fix = Some(fix.into());
        self
    }
}

impl std::fmt::Display for Check {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let tag = match self.verdict {
            Verdict::Ok => "ok",
            Verdict::Note => "note",
            Verdict::Warn => "warn",
            Verdict::Fail => "FAIL",
        };
        write!(f, "{tag:<5} {}: {}", self.topic, self.what)?;
        if let Some(fix) = &self.fix {
            write!(f, "\n      fix: {fix}")?;
        }
        Ok(())
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut checks = Vec::new();
    let cfg = match &args.config {
        None => None,
        Some(path) => match RigConfig::load(path) {
            Ok(cfg) => {
                checks.push(Check::new(
                    Verdict::Ok,
                    "config",
                    format!("{} loads", path.display()),
                ));
                Some(cfg)
            }
            Err(e) => {
                checks.push(
                    Check::new(Verdict::Fail, "config", format!("{}: {e}", path.display()))
                        .fix("correct the key it names; the guide's rig.toml chapter lists them"),
                );
                None
            }
        },
    };
    checks.extend(gpu(cfg.as_ref()));
    let devices = cfg.as_ref().map(configured).unwrap_or_default();
    let real = devices.iter().any(|d| d.is_local_hardware());
    checks.push(udev_rules(&args.udev_rules, real));
    if let Some(cfg) = &cfg {
        // Listing USB and HID devices opens libusb and hidapi: only for a rig that has some.
        let found = real.then(|| discovery::discover(&dioptra_rig::devices::open::known_devices()));
        for d in &devices {
            checks.extend(device(d, found.as_ref()));
        }
        checks.push(api_address(cfg));
    }
    for c in &checks {
        println!("{c}");
    }
    let failed = checks.iter().filter(|c| c.verdict == Verdict::Fail).count();
    if failed > 0 {
        return Err(crate::common::Exit::new(
            1,
            format!(
                "dioptra doctor: {failed} check{} failed: fix {} and run it again",
                if failed == 1 { "" } else { "s" },
                if failed == 1 { "it" } else { "them" },
            ),
        )
        .into());
    }
    Ok(())
}

/// The GPU adapters wgpu finds (the renderer's and the window's): hardware, software, none.
fn gpu(cfg: Option<&RigConfig>) -> Vec<Check> {
    let backend = cfg.map_or(RenderBackend::Auto, |c| c.render.backend);
    let window = cfg.is_some_and(|c| c.display.kind == SinkKind::Window);
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    let adapters =
        pollster::block_on(wgpu::Instance::new(desc).enumerate_adapters(desc_backends()));
    let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
    gpu_checks(&infos, backend, window)
}

fn desc_backends() -> wgpu::Backends {
    wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12
}

const GPU_FIX: &str = "install the GPU's Vulkan driver (AMD, Intel: sudo apt install \
                       mesa-vulkan-drivers; NVIDIA: the vendor's driver) and check it with \
                       `vulkaninfo --summary` (package vulkan-tools)";

fn gpu_checks(infos: &[wgpu::AdapterInfo], backend: RenderBackend, window: bool) -> Vec<Check> {
    let describe = |i: &wgpu::AdapterInfo| {
        let driver = [i.driver.as_str(), i.driver_info.as_str()]
            .into_iter()
            .filter(|s| !s.is_empty())
            .collect::<Vec<_>>()
            .join(", ");
        format!(
            "{} ({:?}, {:?}; driver {})",
            i.name,
            i.backend,
            i.device_type,
            if driver.is_empty() {
                "not named"
            } else {
                &driver
            }
        )
    };
    let hardware = infos.iter().any(|i| i.device_type != wgpu::DeviceType::Cpu);
    let mut out: Vec<Check> = infos
        .iter()
        .map(|i| {
            let software = i.device_type == wgpu::DeviceType::Cpu;
            let verdict = if software && !hardware && backend != RenderBackend::Cpu {
                Verdict::Warn
            } else if software {
                Verdict::Note
            } else {
                Verdict::Ok
            };
            let mut c = Check::new(verdict, "gpu", describe(i));
            if verdict == Verdict::Warn {
                c.what += match backend {
                    RenderBackend::Gpu => ": the only adapter, a software one: render.backend = \"gpu\" renders on the CPU's rasteriser, slowly",
                    _ => ": the only adapter, a software one: render.backend = \"auto\" renders on the CPU",
                };
                c = c.fix(GPU_FIX);
            }
            c
        })
        .collect();
    if infos.is_empty() {
        let needed = backend == RenderBackend::Gpu || window;
        let why = if backend == RenderBackend::Gpu {
            "no GPU adapter (Vulkan): render.backend = \"gpu\" cannot start"
        } else if window {
            "no GPU adapter (Vulkan): display.kind = \"window\" draws with one and cannot start"
        } else {
            "no GPU adapter (Vulkan): the rig renders on the CPU"
        };
        out.push(
            Check::new(
                if needed { Verdict::Fail } else { Verdict::Warn },
                "gpu",
                why,
            )
            .fix(GPU_FIX),
        );
    }
    out
}

/// The udev rules installed at `path` against what `dioptra udev` prints now: the seat
/// variant (uaccess) or the group variant (`--group NAME`, a service's). `devices`: the rig
/// has local serial, USB or HID devices, which stay root's without rules.
fn udev_rules(path: &Path, devices: bool) -> Check {
    let table = dioptra_rig::devices::open::known_devices();
    let missing = if devices {
        Verdict::Fail
    } else {
        Verdict::Warn
    };
    let install = |group: Option<&str>| {
        let flag = group.map(|g| format!(" --group {g}")).unwrap_or_default();
        format!(
            "dioptra udev{flag} | sudo tee {} && sudo udevadm control --reload && sudo udevadm trigger",
            path.display()
        )
    };
    let installed = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Check::new(
                missing,
                "udev rules",
                format!(
                    "{} is not installed: serial, USB and HID devices stay root's",
                    path.display()
                ),
            )
            .fix(
                install(Some("dioptra"))
                    + " (as a service; for the logged-in user: without --group)",
            );
        }
        Err(e) => {
            return Check::new(missing, "udev rules", format!("{}: {e}", path.display()))
                .fix(format!("sudo chmod a+r {}", path.display()));
        }
    };
    let group = rules_group(&installed);
    let fresh = crate::udev::rules(&table, group.as_deref());
    if installed != fresh {
        return Check::new(
            missing,
            "udev rules",
            format!(
                "{} differs from what `dioptra udev{}` prints: out of date (a driver was added or changed) or edited",
                path.display(),
                group.as_ref().map(|g| format!(" --group {g}")).unwrap_or_default()
            ),
        )
        .fix(install(group.as_deref()));
    }
    match group {
        None => Check::new(
            Verdict::Ok,
            "udev rules",
            format!(
                "{} is up to date; it gives the user logged in at the seat access (uaccess), not a service's user",
                path.display()
            ),
        ),
        Some(g) => match member_of(&g) {
            Membership::Member | Membership::Root => Check::new(
                Verdict::Ok,
                "udev rules",
                format!(
                    "{} is up to date and gives group {g} access; {} is in it",
                    path.display(),
                    user_name()
                ),
            ),
            Membership::NoSuchGroup => Check::new(
                Verdict::Fail,
                "udev rules",
                format!("{} gives group {g} access, and there is no group {g}", path.display()),
            )
            .fix(format!(
                "sudo groupadd --system {g} && sudo usermod -aG {g} {} && sudo udevadm trigger",
                user_name()
            )),
            Membership::NotMember => Check::new(
                if devices { Verdict::Fail } else { Verdict::Warn },
                "udev rules",
                format!(
                    "{} gives group {g} access, and {} is not in group {g}",
                    path.display(),
                    user_name()
                ),
            )
            .fix(format!(
                "sudo usermod -aG {g} {}, then log in again (a service: restart it)",
                user_name()
            )),
        },
    }
}

/// The group a rules file grants access to (`GROUP="NAME"`), if it is the group variant.
fn rules_group(text: &str) -> Option<String> {
    let rest = text.split("GROUP=\"").nth(1)?;
    Some(rest.split('"').next()?.to_string())
}

/// A device the config names.
struct Configured {
    /// Its config section: `devices.lens`, `devices.lens.left`, ...
    section: String,
    /// None: the photodiode on the sync board's input, which has no port of its own.
    port: Option<Port>,
}

impl Configured {
    /// A device on this machine's serial, USB or HID buses (not simulated, not on the network).
    fn is_local_hardware(&self) -> bool {
        matches!(
            self.port,
            Some(Port::Path(_) | Port::VidPid(..) | Port::Usb(_))
        )
    }
}

fn configured(cfg: &RigConfig) -> Vec<Configured> {
    let mut out: Vec<Configured> = cfg
        .devices
        .list()
        .into_iter()
        .map(|d| Configured {
            section: d.section,
            port: Some(d.port),
        })
        .collect();
    if let Some(p) = &cfg.devices.photodiode {
        out.push(Configured {
            section: "devices.photodiode".into(),
            port: p.port.clone(),
        });
    }
    out
}

/// Whether a configured device is there and this user may open it; then who it is.
fn device(d: &Configured, found: Option<&Discovery>) -> Vec<Check> {
    let key = format!("{}.port", d.section);
    let Some(port) = &d.port else {
        return vec![Check::new(
            Verdict::Ok,
            &d.section,
            "no port of its own: the input of the [devices.sync] board",
        )];
    };
    let none = Discovery::default();
    let found = found.unwrap_or(&none);
    let (presence, unit) = match port {
        Port::Sim => {
            return vec![Check::new(
                Verdict::Ok,
                &d.section,
                "simulated (port = \"sim\"): no device to check",
            )]
        }
        Port::Net(addr) => return vec![network(&d.section, addr)],
        Port::Path(path) => path_device(&key, path, found),
        Port::VidPid(vid, pid) => {
            let matching: Vec<&FoundDevice> = found
                .devices
                .iter()
                .filter(|f| f.vid == Some(*vid) && f.pid == Some(*pid))
                .collect();
            match matching.as_slice() {
                [] => (
                    Check::new(
                        Verdict::Fail,
                        &d.section,
                        format!("no device with USB id {vid:04x}:{pid:04x} ({key}) is plugged in"),
                    )
                    .fix(format!(
                        "plug it in and check that `dioptra devices` lists it; {}",
                        found_notes(found)
                    )),
                    None,
                ),
                [one] => (access_of(&key, &one.location, Some(one)), Some(*one)),
                many => (
                    Check::new(
                        Verdict::Fail,
                        &d.section,
                        format!(
                            "{} devices have USB id {vid:04x}:{pid:04x} ({key}): {}; a VID:PID names one",
                            many.len(),
                            many.iter().map(|f| f.location.as_str()).collect::<Vec<_>>().join(", ")
                        ),
                    )
                    .fix(format!("set {key} to one device's path, e.g. its /dev/serial/by-id/ link")),
                    None,
                ),
            }
        }
        Port::Usb(serial) => {
            let bulk: Vec<&FoundDevice> = found
                .devices
                .iter()
                .filter(|f| f.interface == Interface::UsbBulk && f.known.is_some())
                .filter(|f| serial.is_none() || f.serial == *serial)
                .collect();
            match bulk.first() {
                None => (
                    Check::new(
                        Verdict::Fail,
                        &d.section,
                        format!("no USB device dioptra drives over bulk endpoints matches {key} = \"{port}\""),
                    )
                    .fix(format!(
                        "plug it in and check that `dioptra devices` lists it; {}",
                        found_notes(found)
                    )),
                    None,
                ),
                Some(f) => (access_of(&key, &usb_node(&f.location), Some(f)), Some(*f)),
            }
        }
    };
    let mut out = vec![presence];
    if out[0].verdict != Verdict::Fail || unit.is_some() {
        out.push(identity(&d.section, unit));
    }
    out
}

/// A device at a path: there, and readable and writable by this user.
fn path_device<'a>(
    key: &str,
    path: &Path,
    found: &'a Discovery,
) -> (Check, Option<&'a FoundDevice>) {
    let section = key.trim_end_matches(".port");
    if !path.exists() {
        let by_id = if path.starts_with("/dev/serial/by-id") {
            ""
        } else {
            "; a /dev/serial/by-id/ path stays the same whatever tty the device gets"
        };
        return (
            Check::new(
                Verdict::Fail,
                section,
                format!("{} ({key}) is not present", path.display()),
            )
            .fix(format!(
                "plug the device in and run `dioptra devices` to see where it is; set {key} to that path{by_id}"
            )),
            None,
        );
    }
    let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let unit = found
        .devices
        .iter()
        .find(|f| Path::new(&f.location) == real || Path::new(&f.location) == path);
    (access_of(key, &path.to_string_lossy(), unit), unit)
}

/// `/dev/bus/usb/BBB/DDD` for discovery's "USB bus BBB device DDD".
fn usb_node(location: &str) -> String {
    let mut words = location.split_whitespace();
    match (words.nth(2), words.nth(1)) {
        (Some(bus), Some(dev)) => format!("/dev/bus/usb/{bus}/{dev}"),
        _ => location.to_string(),
    }
}

/// Whether this user may read and write the device node `node`.
fn access_of(key: &str, node: &str, unit: Option<&FoundDevice>) -> Check {
    let section = key.trim_end_matches(".port");
    let who = unit.map(describe_unit).unwrap_or_default();
    let Ok(c_path) = std::ffi::CString::new(node) else {
        return Check::new(Verdict::Fail, section, format!("{node:?} is not a path"));
    };
    // SAFETY: access(2) on a NUL-terminated path; it reads nothing else.
    let rw = unsafe { libc::access(c_path.as_ptr(), libc::R_OK | libc::W_OK) } == 0;
    if rw {
        return Check::new(
            Verdict::Ok,
            section,
            format!(
                "{node}{who}: present, readable and writable by {}",
                user_name()
            ),
        );
    }
    let group = file_group(Path::new(node));
    let fix = match group.as_deref() {
        Some("root") | None => "install the udev rules (see the udev rules line) and replug the device".to_string(),
        Some(g) => format!(
            "sudo usermod -aG {g} {}, then log in again (a service: add {g} to its SupplementaryGroups= or use the dioptra group's rules)",
            user_name()
        ),
    };
    Check::new(
        Verdict::Fail,
        section,
        format!(
            "{node}{who} is there, and {} may not read and write it (group {})",
            user_name(),
            group.as_deref().unwrap_or("unknown")
        ),
    )
    .fix(fix)
}

fn describe_unit(f: &FoundDevice) -> String {
    let mut parts = Vec::new();
    if let (Some(v), Some(p)) = (f.vid, f.pid) {
        parts.push(format!("USB {v:04x}:{p:04x}"));
    }
    if let Some(k) = &f.known {
        parts.push(k.name.to_string());
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!(" ({})", parts.join(", "))
    }
}

/// Which unit answers for the device. The config names a device by its port only; the line
/// says what serial number the unit there reports, so that a lab sees which one it is.
fn identity(section: &str, unit: Option<&FoundDevice>) -> Check {
    let reported = match unit.and_then(|u| u.serial.as_deref()) {
        Some(s) => format!("; the device there reports serial number {s}"),
        None => String::new(),
    };
    Check::new(
        Verdict::Note,
        section,
        format!("serial number: not configured (the device is found by its port){reported}"),
    )
}

fn found_notes(found: &Discovery) -> String {
    if found.notes.is_empty() {
        "a USB cable or hub may be at fault (dmesg shows what the kernel saw)".into()
    } else {
        format!("while listing devices: {}", found.notes.join("; "))
    }
}

/// A network device (Pupil Capture's Pupil Remote): something listens at its address.
fn network(section: &str, addr: &str) -> Check {
    use std::net::ToSocketAddrs;
    let timeout = std::time::Duration::from_secs(1);
    let reached = addr
        .to_socket_addrs()
        .ok()
        .into_iter()
        .flatten()
        .any(|a| std::net::TcpStream::connect_timeout(&a, timeout).is_ok());
    if reached {
        Check::new(Verdict::Ok, section, format!("{addr} answers"))
    } else {
        Check::new(
            Verdict::Fail,
            section,
            format!("nothing answers at {addr} ({section}.port)"),
        )
        .fix("start Pupil Capture (or Pupil Service) with its Pupil Remote plugin on, at this address and port")
    }
}

/// The API's address is free to bind (or a Unix socket's folder takes it).
fn api_address(cfg: &RigConfig) -> Check {
    match cfg.api.listen() {
        Err(e) => Check::new(Verdict::Fail, "api", e.to_string()).fix("correct the key it names"),
        Ok(Listen::Tcp(addr)) => match std::net::TcpListener::bind(addr) {
            Ok(_) => Check::new(Verdict::Ok, "api.listen", format!("{addr} is free")),
            Err(e) => Check::new(
                Verdict::Fail,
                "api.listen",
                format!("cannot listen on {addr}: {e}"),
            )
            .fix(format!(
                "stop what listens there (another daemon: `systemctl stop dioptra`; find it with `ss -ltnp 'sport = :{}'`) or set api.listen to another port",
                addr.port()
            )),
        },
        Ok(Listen::Unix(path)) => {
            if std::os::unix::net::UnixStream::connect(&path).is_ok() {
                return Check::new(
                    Verdict::Fail,
                    "api.unix",
                    format!("a daemon already answers on {}", path.display()),
                )
                .fix("stop it (`systemctl stop dioptra`, or POST /shutdown) or set api.unix to another path");
            }
            let dir = path.parent().unwrap_or(Path::new("."));
            let Ok(c_dir) = std::ffi::CString::new(dir.as_os_str().as_encoded_bytes()) else {
                return Check::new(Verdict::Fail, "api.unix", format!("{} is not a path", dir.display()));
            };
            // SAFETY: access(2) on a NUL-terminated path.
            if unsafe { libc::access(c_dir.as_ptr(), libc::W_OK | libc::X_OK) } == 0 {
                Check::new(
                    Verdict::Ok,
                    "api.unix",
                    format!("{} can be created", path.display()),
                )
            } else {
                Check::new(
                    Verdict::Fail,
                    "api.unix",
                    format!("{} cannot be created: {} may not write {}", path.display(), user_name(), dir.display()),
                )
                .fix("choose a folder this user owns (a service: RuntimeDirectory=dioptra gives it /run/dioptra)")
            }
        }
    }
}

fn user_name() -> String {
    std::env::var("USER")
        .ok()
        .filter(|u| !u.is_empty())
        // SAFETY: getuid(2) cannot fail.
        .unwrap_or_else(|| format!("uid {}", unsafe { libc::getuid() }))
}

enum Membership {
    Member,
    NotMember,
    NoSuchGroup,
    /// Root opens every device whatever its group.
    Root,
}

fn member_of(group: &str) -> Membership {
    // SAFETY: geteuid(2) cannot fail.
    if unsafe { libc::geteuid() } == 0 {
        return Membership::Root;
    }
    let Ok(name) = std::ffi::CString::new(group) else {
        return Membership::NoSuchGroup;
    };
    // SAFETY: getgrnam(3) with a NUL-terminated name; the entry is read at once, before any
    // other call could reuse its static storage (doctor runs these on one thread).
    let gid = unsafe {
        let entry = libc::getgrnam(name.as_ptr());
        if entry.is_null() {
            return Membership::NoSuchGroup;
        }
        (*entry).gr_gid
    };
    // SAFETY: getgroups(2) with a buffer of the size it was asked for.
    let groups = unsafe {
        let n = libc::getgroups(0, std::ptr::null_mut());
        let mut v = vec![0 as libc::gid_t; n.max(0) as usize];
        let n = libc::getgroups(n, v.as_mut_ptr());
        v.truncate(n.max(0) as usize);
        v
    };
    // SAFETY: getegid(2) cannot fail.
    if groups.contains(&gid) || unsafe { libc::getegid() } == gid {
        Membership::Member
    } else {
        Membership::NotMember
    }
}

/// The name of the group that owns `path`.
fn file_group(path: &Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let gid = std::fs::metadata(path).ok()?.gid();
    // SAFETY: getgrgid(3); the name is copied out at once (one thread).
    unsafe {
        let entry = libc::getgrgid(gid);
        if entry.is_null() {
            return Some(gid.to_string());
        }
        Some(
            std::ffi::CStr::from_ptr((*entry).gr_name)
                .to_string_lossy()
                .into_owned(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn adapter(name: &str, device_type: wgpu::DeviceType) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo {
            name: name.into(),
            driver: "driver".into(),
            driver_info: "1.0".into(),
            ..wgpu::AdapterInfo::new(device_type, wgpu::Backend::Vulkan)
        }
    }

    #[test]
    fn a_software_adapter_alone_is_a_warning_with_a_fix_and_none_fails_a_gpu_rig() {
        let sw = [adapter("llvmpipe", wgpu::DeviceType::Cpu)];
        let c = gpu_checks(&sw, RenderBackend::Auto, false);
        assert_eq!(c.len(), 1);
        assert_eq!(c[0].verdict, Verdict::Warn, "{}", c[0]);
        assert!(c[0].fix.as_deref().unwrap().contains("mesa-vulkan-drivers"));
        assert!(c[0].what.contains("driver driver, 1.0"), "{}", c[0]);

        let both = [
            adapter("llvmpipe", wgpu::DeviceType::Cpu),
            adapter("Radeon", wgpu::DeviceType::DiscreteGpu),
        ];
        let c = gpu_checks(&both, RenderBackend::Auto, false);
        assert_eq!(
            c.iter().map(|c| c.verdict).collect::<Vec<_>>(),
            [Verdict::Note, Verdict::Ok]
        );

        assert_eq!(
            gpu_checks(&[], RenderBackend::Auto, false)[0].verdict,
            Verdict::Warn
        );
        assert_eq!(
            gpu_checks(&[], RenderBackend::Gpu, false)[0].verdict,
            Verdict::Fail
        );
        assert_eq!(
            gpu_checks(&[], RenderBackend::Cpu, true)[0].verdict,
            Verdict::Fail
        );
    }

    #[test]
    fn the_rules_group_is_read_from_the_group_variant_only() {
        let table = dioptra_rig::devices::open::known_devices();
        assert_eq!(
            rules_group(&crate::udev::rules(&table, Some("lab-rig"))).as_deref(),
            Some("lab-rig")
        );
        assert_eq!(rules_group(&crate::udev::rules(&table, None)), None);
    }

    #[test]
    fn a_usb_location_maps_to_its_device_node() {
        assert_eq!(usb_node("USB bus 001 device 004"), "/dev/bus/usb/001/004");
    }

    #[test]
    fn every_line_that_is_not_ok_prints_its_fix() {
        let c = Check::new(Verdict::Fail, "devices.lens", "gone").fix("plug it in");
        assert_eq!(
            c.to_string(),
            "FAIL  devices.lens: gone\n      fix: plug it in"
        );
    }
}
