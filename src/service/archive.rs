//! A whole scan directory as a zip file, written as a stream (for `GET .../archive.zip`).
//!
//! Entries are stored (no compression: frames are PNG and models are binary, compression would
//! win little and cost CPU on a small box). Each file is opened once, read once for its CRC-32,
//! rewound and read again into the output, so the local header carries the size and CRC and no
//! data descriptor is needed; memory is one 64 KiB buffer whatever the sizes. Files are listed in
//! name order, directories recursed, temporary files of atomic writes skipped. No Zip64: a file
//! or an archive of 4 GiB or more, or more than 65535 entries, is refused.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Why the archive could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// A file or directory could not be read.
    #[error("cannot read {path}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The output could not be written (the client went away).
    #[error("cannot write the archive")]
    Write(#[source] std::io::Error),
    /// Past what a zip without Zip64 holds.
    #[error("{0} is too large for a zip without Zip64 (4 GiB per file and in all, 65535 entries)")]
    TooLarge(String),
    /// A file changed size while it was archived.
    #[error("{0} changed while it was archived")]
    Changed(PathBuf),
}

struct Entry {
    name: String,
    crc: u32,
    size: u32,
    offset: u32,
    time: u16,
    date: u16,
}

/// Counts the bytes written through it.
struct Counting<W> {
    inner: W,
    written: u64,
}

impl<W: Write> Counting<W> {
    fn put(&mut self, bytes: &[u8]) -> Result<(), ArchiveError> {
        self.inner.write_all(bytes).map_err(ArchiveError::Write)?;
        self.written += bytes.len() as u64;
        Ok(())
    }
}

/// Every file under `dir`, relative names with `/`, sorted, without atomic-write temporaries.
pub fn list_files(dir: &Path) -> Result<Vec<(String, PathBuf)>, ArchiveError> {
    fn walk(dir: &Path, prefix: &str, out: &mut Vec<(String, PathBuf)>) -> Result<(), ArchiveError> {
        let read = std::fs::read_dir(dir).map_err(|source| ArchiveError::Read { path: dir.to_owned(), source })?;
        let mut entries: Vec<_> = read.flatten().collect();
        entries.sort_by_key(|e| e.file_name());
        for e in entries {
            let name = e.file_name().to_string_lossy().into_owned();
            if crate::atomic::is_atomic_temp(&name) {
                continue;
            }
            let path = e.path();
            let kind = e.file_type().map_err(|source| ArchiveError::Read { path: path.clone(), source })?;
            if kind.is_dir() {
                walk(&path, &format!("{prefix}{name}/"), out)?;
            } else if kind.is_file() {
                out.push((format!("{prefix}{name}"), path));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, "", &mut out)?;
    Ok(out)
}

/// Write every file under `dir` into `out` as a zip archive (see the module docs). Returns the
/// number of bytes written.
pub fn write_dir_zip(dir: &Path, out: impl Write) -> Result<u64, ArchiveError> {
    let files = list_files(dir)?;
    if files.len() > 0xffff {
        return Err(ArchiveError::TooLarge(dir.display().to_string()));
    }
    let mut w = Counting { inner: std::io::BufWriter::with_capacity(64 * 1024, out), written: 0 };
    let mut entries = Vec::with_capacity(files.len());
    let mut buf = vec![0u8; 64 * 1024];
    for (name, path) in files {
        let read_err = |source| ArchiveError::Read { path: path.clone(), source };
        let mut f = std::fs::File::open(&path).map_err(read_err)?;
        let meta = f.metadata().map_err(read_err)?;
        let (time, date) = dos_time(meta.modified().ok());
        let mut hasher = crc32fast::Hasher::new();
        let mut size = 0u64;
        loop {
            let n = f.read(&mut buf).map_err(read_err)?;
            if n == 0 {
                break;
            }
            hasher.update(&buf[..n]);
            size += n as u64;
        }
        let size32 = u32::try_from(size).map_err(|_| ArchiveError::TooLarge(name.clone()))?;
        let offset = u32::try_from(w.written).map_err(|_| ArchiveError::TooLarge(dir.display().to_string()))?;
        let e = Entry { name, crc: hasher.finalize(), size: size32, offset, time, date };
        w.put(&local_header(&e))?;
        f.seek(SeekFrom::Start(0)).map_err(read_err)?;
        let mut left = size;
        while left > 0 {
            let want = buf.len().min(usize::try_from(left).unwrap_or(usize::MAX));
            let n = f.read(&mut buf[..want]).map_err(read_err)?;
            if n == 0 {
                return Err(ArchiveError::Changed(path));
            }
            w.put(&buf[..n])?;
            left -= n as u64;
        }
        entries.push(e);
    }
    let cd_start = w.written;
    for e in &entries {
        w.put(&central_header(e))?;
    }
    let cd_size = w.written - cd_start;
    let too_large = || ArchiveError::TooLarge(dir.display().to_string());
    let mut end = Vec::with_capacity(22);
    end.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    end.extend_from_slice(&[0, 0, 0, 0]); // this disk, the disk with the central directory
    let count = entries.len() as u16;
    end.extend_from_slice(&count.to_le_bytes());
    end.extend_from_slice(&count.to_le_bytes());
    end.extend_from_slice(&u32::try_from(cd_size).map_err(|_| too_large())?.to_le_bytes());
    end.extend_from_slice(&u32::try_from(cd_start).map_err(|_| too_large())?.to_le_bytes());
    end.extend_from_slice(&0u16.to_le_bytes()); // comment length
    w.put(&end)?;
    w.inner.flush().map_err(ArchiveError::Write)?;
    Ok(w.written)
}

/// Version needed to extract: 2.0 (stored entries, directories in names).
const VERSION: u16 = 20;
/// General purpose flag bit 11: names are UTF-8.
const UTF8: u16 = 1 << 11;

fn local_header(e: &Entry) -> Vec<u8> {
    let mut h = Vec::with_capacity(30 + e.name.len());
    h.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
    h.extend_from_slice(&VERSION.to_le_bytes());
    h.extend_from_slice(&UTF8.to_le_bytes());
    h.extend_from_slice(&0u16.to_le_bytes()); // stored
    h.extend_from_slice(&e.time.to_le_bytes());
    h.extend_from_slice(&e.date.to_le_bytes());
    h.extend_from_slice(&e.crc.to_le_bytes());
    h.extend_from_slice(&e.size.to_le_bytes());
    h.extend_from_slice(&e.size.to_le_bytes());
    h.extend_from_slice(&(e.name.len() as u16).to_le_bytes());
    h.extend_from_slice(&0u16.to_le_bytes()); // extra
    h.extend_from_slice(e.name.as_bytes());
    h
}

fn central_header(e: &Entry) -> Vec<u8> {
    let mut h = Vec::with_capacity(46 + e.name.len());
    h.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
    h.extend_from_slice(&((3u16 << 8) | VERSION).to_le_bytes()); // made by: Unix
    h.extend_from_slice(&VERSION.to_le_bytes());
    h.extend_from_slice(&UTF8.to_le_bytes());
    h.extend_from_slice(&0u16.to_le_bytes());
    h.extend_from_slice(&e.time.to_le_bytes());
    h.extend_from_slice(&e.date.to_le_bytes());
    h.extend_from_slice(&e.crc.to_le_bytes());
    h.extend_from_slice(&e.size.to_le_bytes());
    h.extend_from_slice(&e.size.to_le_bytes());
    h.extend_from_slice(&(e.name.len() as u16).to_le_bytes());
    h.extend_from_slice(&[0; 8]); // extra, comment, disk, internal attributes
    h.extend_from_slice(&(0o100_644u32 << 16).to_le_bytes()); // a regular file, rw-r--r--
    h.extend_from_slice(&e.offset.to_le_bytes());
    h.extend_from_slice(e.name.as_bytes());
    h
}

/// A modification time as MS-DOS time and date (UTC, two-second resolution, 1980 to 2107).
fn dos_time(t: Option<std::time::SystemTime>) -> (u16, u16) {
    let secs = t.and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map_or(0, |d| d.as_secs());
    let c = super::store::civil(secs);
    if c.year < 1980 {
        return (0, (1 << 5) | 1); // 1980-01-01 00:00
    }
    let year = (c.year - 1980).min(127) as u16;
    let time = ((c.hour as u16) << 11) | ((c.minute as u16) << 5) | (c.second as u16 / 2);
    let date = (year << 9) | ((c.month as u16) << 5) | c.day as u16;
    (time, date)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_directory_round_trips_through_unzip() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir(dir.path().join("frames")).expect("mkdir");
        std::fs::write(dir.path().join("report.json"), b"{\"views\": 3}").expect("write");
        let big: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(dir.path().join("frames/pos_000.png"), &big).expect("write");
        std::fs::write(dir.path().join("frames/.x.tmp-1"), b"partial").expect("write");
        std::fs::write(dir.path().join("empty"), b"").expect("write");
        let mut zip = Vec::new();
        let n = write_dir_zip(dir.path(), &mut zip).expect("zip");
        assert_eq!(n as usize, zip.len());
        let out = tempfile::tempdir().expect("tempdir");
        let path = out.path().join("a.zip");
        std::fs::write(&path, &zip).expect("write");
        let test = std::process::Command::new("unzip").arg("-t").arg(&path).output().expect("unzip is installed");
        assert!(test.status.success(), "{}", String::from_utf8_lossy(&test.stdout));
        let ex = std::process::Command::new("unzip")
            .arg("-q")
            .arg(&path)
            .arg("-d")
            .arg(out.path().join("x"))
            .status()
            .expect("unzip");
        assert!(ex.success());
        assert_eq!(std::fs::read(out.path().join("x/frames/pos_000.png")).expect("read"), big);
        assert_eq!(std::fs::read(out.path().join("x/report.json")).expect("read"), b"{\"views\": 3}");
        assert!(out.path().join("x/empty").is_file());
        assert!(!out.path().join("x/frames/.x.tmp-1").exists(), "temporaries are left out");
    }

    #[test]
    fn dos_times_encode_the_civil_date() {
        // 2026-12-02 01:02:04 UTC
        let t = std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_796_173_324);
        let (time, date) = dos_time(Some(t));
        assert_eq!(date >> 9, 2026 - 1980);
        assert_eq!((date >> 5) & 0xf, 12);
        assert_eq!(date & 0x1f, 2);
        assert_eq!(time >> 11, 1);
        assert_eq!((time >> 5) & 0x3f, 2);
        assert_eq!((time & 0x1f) * 2, 4);
    }
}
