//! The real PX4 autopilot as part of a stack: finding a PX4 SITL build (SIH, headless), making
//! it runnable, choosing instance numbers, and the command line of each instance.
//!
//! PX4 SITL instance `i` binds its offboard link on UDP 14580+i and its GCS link on 18570+i
//! (PX4's start-up scripts fix them), has MAV_SYS_ID i+1, and answers the first address that
//! talks to it. Each vehicle is spawned at its pad: SIH takes the spawn point as a geodetic
//! position (`PX4_HOME_LAT/LON/ALT`), and its local NED origin is that spawn point, which is
//! what the writer's `--home` means.

use super::LaunchError;
use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use tacos_shared::Vec3;
use tacos_shared::frames::SIH_ORIGIN;

/// PX4's offboard (API) link of instance 0; instance i uses this + i.
pub const OFFBOARD_PORT: u16 = 14580;
/// PX4's GCS link of instance 0; instance i uses this + i.
pub const GCS_PORT: u16 = 18570;
/// Instance numbers this launcher picks from (PX4 sends every instance ≥ 10 to one port, and
/// the ports of higher instances run into other services' ranges).
pub const MAX_INSTANCE: u16 = 40;
/// The SIH airframe.
pub const MODEL: &str = "sihsim_quadx";
/// Where to read how to get PX4 SITL.
pub const HOW_TO_GET: &str = "a PX4 SITL build with SIH: bin/px4 and etc/ (PX4-Autopilot, `make px4_sitl_default`, or the bundle in ../shared/px4-sitl); pass --px4-sitl DIR or set TACOS_PX4_SITL";

/// Where a PX4 SITL build is: `flag`, else `$TACOS_PX4_SITL`, else `../shared/px4-sitl` beside
/// the working directory, beside the repository the binaries were built in, or beside the one
/// this crate was compiled from (a `CARGO_TARGET_DIR` outside the repository).
pub fn find_px4_sitl(flag: Option<&Path>) -> Result<PathBuf, LaunchError> {
    let valid = |dir: &Path| dir.join("bin/px4").is_file() && dir.join("etc").is_dir();
    if let Some(dir) = flag {
        return if valid(dir) {
            Ok(dir.to_path_buf())
        } else {
            Err(LaunchError::Config(format!(
                "--px4-sitl {}: no bin/px4 and etc/ there; expected {HOW_TO_GET}",
                dir.display()
            )))
        };
    }
    if let Some(dir) = std::env::var_os("TACOS_PX4_SITL") {
        let dir = PathBuf::from(dir);
        return if valid(&dir) {
            Ok(dir)
        } else {
            Err(LaunchError::Config(format!(
                "TACOS_PX4_SITL={}: no bin/px4 and etc/ there; expected {HOW_TO_GET}",
                dir.display()
            )))
        };
    }
    let mut candidates = vec![PathBuf::from("../shared/px4-sitl")];
    // target/<profile>/ → the repository → its sibling shared/.
    if let Some(repo) = super::bin_dir().parent().and_then(Path::parent) {
        candidates.push(repo.join("../shared/px4-sitl"));
    }
    candidates.push(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/px4-sitl"));
    candidates
        .into_iter()
        .find(|d| valid(d))
        .map(|d| d.canonicalize().unwrap_or(d))
        .ok_or_else(|| LaunchError::Config(format!("no PX4 SITL found: {HOW_TO_GET}")))
}

/// A PX4 SITL build made runnable in `run_dir`: PX4 runs its modules as `px4-<module>` commands
/// beside its binary, which a copy without symbolic links (or a read-only one) lacks, so a
/// `bin/` of links to the build's binary is laid out here.
#[derive(Debug, Clone)]
pub struct Px4Bundle {
    /// The `px4` to run.
    pub px4: PathBuf,
    /// PX4's ROMFS (`etc/`), the last argument of every instance.
    pub etc: PathBuf,
    /// Where the instances' working directories go.
    pub run_dir: PathBuf,
}

fn io_error(what: &str, path: &Path, e: std::io::Error) -> LaunchError {
    LaunchError::Config(format!("{what} {}: {e}", path.display()))
}

/// Lays out `run_dir/bin` for the build in `sitl_dir`.
pub fn prepare(sitl_dir: &Path, run_dir: &Path) -> Result<Px4Bundle, LaunchError> {
    let sitl_dir = sitl_dir
        .canonicalize()
        .map_err(|e| io_error("PX4 SITL folder", sitl_dir, e))?;
    let bin = run_dir.join("bin");
    if bin.exists() {
        std::fs::remove_dir_all(&bin).map_err(|e| io_error("clearing", &bin, e))?;
    }
    std::fs::create_dir_all(&bin).map_err(|e| io_error("creating", &bin, e))?;
    let source_bin = sitl_dir.join("bin");
    let px4 = bin.join("px4");
    std::os::unix::fs::symlink(source_bin.join("px4"), &px4)
        .map_err(|e| io_error("linking", &px4, e))?;
    let entries =
        std::fs::read_dir(&source_bin).map_err(|e| io_error("reading", &source_bin, e))?;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(text) = name.to_str() else { continue };
        if !text.starts_with("px4-") {
            continue;
        }
        let target = bin.join(text);
        if text.ends_with(".sh") {
            // px4-alias.sh is a script PX4 sources: copied as is.
            std::fs::copy(entry.path(), &target).map_err(|e| io_error("copying", &target, e))?;
        } else {
            std::os::unix::fs::symlink("px4", &target)
                .map_err(|e| io_error("linking", &target, e))?;
        }
    }
    Ok(Px4Bundle {
        px4,
        etc: sitl_dir.join("etc"),
        run_dir: run_dir.to_path_buf(),
    })
}

/// The first instance number from which `n` instances find all their ports free.
pub fn free_instance_base(n: usize) -> Result<u16, LaunchError> {
    let free = |port: u16| UdpSocket::bind(("127.0.0.1", port)).is_ok();
    let n = u16::try_from(n).map_err(|_| LaunchError::Config("too many PX4 instances".into()))?;
    (0..=MAX_INSTANCE.saturating_sub(n))
        .find(|base| {
            (*base..base + n)
                .all(|i| free(OFFBOARD_PORT + i) && free(GCS_PORT + i) && free(14540 + i))
        })
        .ok_or(LaunchError::NoFreePort {
            what: "PX4 SITL instance",
        })
}

/// What one PX4 instance is started with.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceLaunch {
    pub instance: u16,
    pub cwd: PathBuf,
    pub args: Vec<String>,
    pub env: Vec<(String, String)>,
}

/// Instance `instance` spawned at the pad `home` (world ENU).
pub fn instance(bundle: &Px4Bundle, instance: u16, home: &Vec3) -> InstanceLaunch {
    let (lat, lon, alt) = SIH_ORIGIN.to_geodetic(home);
    InstanceLaunch {
        instance,
        cwd: bundle.run_dir.join(format!("instance_{instance}")),
        args: vec![
            "-d".into(),
            "-i".into(),
            instance.to_string(),
            bundle.etc.display().to_string(),
        ],
        env: vec![
            ("PX4_SIM_MODEL".into(), MODEL.into()),
            ("PX4_HOME_LAT".into(), format!("{lat:.9}")),
            ("PX4_HOME_LON".into(), format!("{lon:.9}")),
            ("PX4_HOME_ALT".into(), format!("{alt:.3}")),
            // Flight logs are 7-33 MB each: none in a demo or a test.
            ("PX4_PARAM_SDLOG_MODE".into(), "-1".into()),
            // Offboard lost (the writer died): hold, not PX4's default return-to-launch, which
            // climbs to 60 m and flies home outside the planner's deconfliction.
            ("PX4_PARAM_COM_OBL_RC_ACT".into(), "5".into()),
        ],
    }
}

/// The system id PX4 SITL gives instance `instance`.
pub fn sysid(instance: u16) -> u16 {
    instance + 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bundle_links_every_module_command_to_the_binary() {
        let src = std::env::temp_dir().join(format!("tacos-px4-src-{}", std::process::id()));
        let run = std::env::temp_dir().join(format!("tacos-px4-run-{}", std::process::id()));
        std::fs::create_dir_all(src.join("bin")).expect("mkdir");
        std::fs::create_dir_all(src.join("etc")).expect("mkdir");
        std::fs::write(src.join("bin/px4"), b"\x7fELF").expect("write");
        // As a copy without links leaves them: three bytes naming the target.
        std::fs::write(src.join("bin/px4-commander"), b"px4").expect("write");
        std::fs::write(src.join("bin/px4-alias.sh"), b"#!/bin/sh\n").expect("write");
        let bundle = prepare(&src, &run).expect("prepare");
        let link = std::fs::read_link(run.join("bin/px4-commander")).expect("a link");
        assert_eq!(link, PathBuf::from("px4"));
        assert_eq!(
            std::fs::read(run.join("bin/px4-commander")).expect("read"),
            b"\x7fELF"
        );
        assert_eq!(
            std::fs::read(run.join("bin/px4-alias.sh")).expect("read"),
            b"#!/bin/sh\n"
        );
        // Prepared twice (a second demo in the same folder) is fine.
        prepare(&src, &run).expect("prepare again");
        let launch = instance(&bundle, 3, &Vec3::new(10.0, 0.0, 0.0));
        assert_eq!(
            launch.args,
            vec!["-d", "-i", "3", &bundle.etc.display().to_string()]
        );
        assert!(
            launch
                .env
                .iter()
                .any(|(k, v)| k == "PX4_HOME_ALT" && v == "489.400")
        );
        assert_eq!(sysid(3), 4);
        let _ = std::fs::remove_dir_all(&src);
        let _ = std::fs::remove_dir_all(&run);
    }

    #[test]
    fn a_missing_build_says_how_to_get_one() {
        let err = find_px4_sitl(Some(Path::new("/nonexistent/px4"))).expect_err("missing");
        assert!(err.to_string().contains("TACOS_PX4_SITL"), "{err}");
    }
}
