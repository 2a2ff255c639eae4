//! The shipped deployment files as a user would take them: the repository's `deploy/` folder,
//! and certificates made by its `deploy/certs.sh`.

use std::path::{Path, PathBuf};

/// The repository's root.
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The text of a shipped `deploy/zenoh/` file.
pub fn shipped_zenoh(file: &str) -> anyhow::Result<String> {
    let path = repo().join("deploy/zenoh").join(file);
    std::fs::read_to_string(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// Runs `deploy/certs.sh` as a user would: a CA in `dir` (reused if there) and a certificate
/// per principal (`name` or `name=address,...`).
pub fn make_certs(dir: &Path, principals: &[&str]) -> anyhow::Result<()> {
    let out = std::process::Command::new("bash")
        .arg(repo().join("deploy/certs.sh"))
        .arg(dir)
        .args(principals)
        .output()?;
    anyhow::ensure!(
        out.status.success(),
        "deploy/certs.sh failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(())
}
