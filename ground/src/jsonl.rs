//! Append-only JSON-lines files (the mission log, the evaluation's runs): opened with a torn
//! tail repaired, read so that one bad line costs that line only, and synced to the disk when
//! the caller says a record matters.
//!
//! A crash or a full disk can leave a last line without its newline. Appending after it would
//! glue the next record onto the fragment and make a bad line in the middle, so opening repairs
//! it: a fragment that is a whole JSON value only lacks its newline and gets it; anything else
//! is cut off.

use serde::de::DeserializeOwned;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::Path;

/// What [`open_append`] did to a torn last line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Repair {
    /// A whole record lacked only its newline; it was added.
    NewlineAdded,
    /// A record cut short; its `bytes` were removed.
    CutOff { bytes: u64 },
}

/// A line [`read`] left out, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// 1-based.
    pub line: usize,
    pub reason: String,
}

/// The records of a file, and the lines that were not records.
#[derive(Debug, Clone, PartialEq)]
pub struct Contents<T> {
    pub records: Vec<T>,
    pub skipped: Vec<Skipped>,
}

/// Opens `path` for appending, creating it (and its folder) when missing, after repairing a
/// torn last line. A newly created file's folder is synced so that the file itself survives a
/// power cut.
pub fn open_append(path: &Path) -> io::Result<(File, Option<Repair>)> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
    if let Some(dir) = dir {
        std::fs::create_dir_all(dir)?;
    }
    let (existed, repair) = match std::fs::read(path) {
        Ok(bytes) => (true, repair_tail(path, &bytes)?),
        Err(e) if e.kind() == io::ErrorKind::NotFound => (false, None),
        Err(e) => return Err(e),
    };
    let file = OpenOptions::new().create(true).append(true).open(path)?;
    if !existed {
        // Best effort: some file systems cannot open a folder for syncing.
        if let Ok(d) = File::open(dir.unwrap_or(Path::new("."))) {
            let _ = d.sync_all();
        }
    }
    Ok((file, repair))
}

fn repair_tail(path: &Path, bytes: &[u8]) -> io::Result<Option<Repair>> {
    if bytes.last().is_none_or(|b| *b == b'\n') {
        return Ok(None);
    }
    let keep = bytes.iter().rposition(|b| *b == b'\n').map_or(0, |i| i + 1);
    let tail = &bytes[keep..];
    if serde_json::from_slice::<serde_json::Value>(tail).is_ok() {
        let mut f = OpenOptions::new().append(true).open(path)?;
        f.write_all(b"\n")?;
        f.sync_data()?;
        return Ok(Some(Repair::NewlineAdded));
    }
    let f = OpenOptions::new().write(true).open(path)?;
    f.set_len(keep as u64)?;
    f.sync_data()?;
    Ok(Some(Repair::CutOff {
        bytes: tail.len() as u64,
    }))
}

/// Writes `record` as one line; with `sync`, waits until it is on the disk (`flush` on a
/// `File` does nothing: the bytes are in the kernel after `write_all`, on the disk only after
/// `sync_data`).
pub fn append<T: serde::Serialize>(file: &mut File, record: &T, sync: bool) -> io::Result<()> {
    let mut text = serde_json::to_string(record).map_err(io::Error::other)?;
    text.push('\n');
    file.write_all(text.as_bytes())?;
    if sync {
        file.sync_data()?;
    }
    Ok(())
}

/// Reads every line of `path` that is a `T`. A line that is not UTF-8 or not a `T` (a record
/// cut short, a partial write on a full disk, a record of another version) is skipped and
/// named in `skipped`; blank lines are ignored.
pub fn read<T: DeserializeOwned>(path: &Path) -> io::Result<Contents<T>> {
    let bytes = std::fs::read(path)?;
    Ok(parse(&bytes))
}

/// [`read`] on bytes already in memory.
pub fn parse<T: DeserializeOwned>(bytes: &[u8]) -> Contents<T> {
    let mut records = Vec::new();
    let mut skipped = Vec::new();
    for (i, raw) in bytes.split(|b| *b == b'\n').enumerate() {
        let line = i + 1;
        let text = match std::str::from_utf8(raw) {
            Ok(t) => t,
            Err(e) => {
                skipped.push(Skipped {
                    line,
                    reason: format!("not UTF-8: {e}"),
                });
                continue;
            }
        };
        if text.trim().is_empty() {
            continue;
        }
        match serde_json::from_str::<T>(text) {
            Ok(r) => records.push(r),
            Err(e) => skipped.push(Skipped {
                line,
                reason: e.to_string(),
            }),
        }
    }
    Contents { records, skipped }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct R {
        n: u32,
        text: String,
    }

    fn r(n: u32) -> R {
        R {
            n,
            text: format!("record {n} ✈"),
        }
    }

    fn scratch(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("tacos-jsonl-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir.join("sub").join("file.jsonl")
    }

    #[test]
    fn a_torn_tail_is_cut_off_on_open_and_the_next_record_starts_on_its_own_line() {
        let path = scratch("torn");
        let (mut f, repair) = open_append(&path).expect("create");
        assert_eq!(repair, None);
        append(&mut f, &r(1), true).expect("append");
        drop(f);
        // Cut inside the multi-byte character of the second record.
        let whole = serde_json::to_vec(&r(2)).expect("json");
        let cut = whole.len() - 4;
        let mut f = OpenOptions::new().append(true).open(&path).expect("open");
        f.write_all(&whole[..cut]).expect("write");
        drop(f);
        let before: Contents<R> = read(&path).expect("read");
        assert_eq!(before.records, vec![r(1)]);
        assert_eq!(before.skipped.len(), 1, "{:?}", before.skipped);
        let (mut f, repair) = open_append(&path).expect("reopen");
        assert_eq!(repair, Some(Repair::CutOff { bytes: cut as u64 }));
        append(&mut f, &r(3), false).expect("append");
        let after: Contents<R> = read(&path).expect("read");
        assert_eq!(after.records, vec![r(1), r(3)]);
        assert!(after.skipped.is_empty(), "{:?}", after.skipped);
    }

    #[test]
    fn a_whole_record_missing_only_its_newline_is_kept() {
        let path = scratch("newline");
        let (mut f, _) = open_append(&path).expect("create");
        append(&mut f, &r(1), false).expect("append");
        f.write_all(&serde_json::to_vec(&r(2)).expect("json"))
            .expect("write");
        drop(f);
        let (mut f, repair) = open_append(&path).expect("reopen");
        assert_eq!(repair, Some(Repair::NewlineAdded));
        append(&mut f, &r(3), false).expect("append");
        let c: Contents<R> = read(&path).expect("read");
        assert_eq!(c.records, vec![r(1), r(2), r(3)]);
    }

    #[test]
    fn a_bad_middle_line_costs_that_line_only() {
        let mut bytes = serde_json::to_vec(&r(1)).expect("json");
        bytes.extend_from_slice(b"\n{\"n\":2,\"te\n\xff\xfe\n\n");
        bytes.extend_from_slice(&serde_json::to_vec(&r(4)).expect("json"));
        bytes.push(b'\n');
        let c: Contents<R> = parse(&bytes);
        assert_eq!(c.records, vec![r(1), r(4)]);
        let lines: Vec<usize> = c.skipped.iter().map(|s| s.line).collect();
        assert_eq!(lines, [2, 3]);
        assert!(
            c.skipped[1].reason.starts_with("not UTF-8"),
            "{:?}",
            c.skipped
        );
    }
}
