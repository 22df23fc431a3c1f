//! The map file (`map.vlem`): a versioned, checksummed, crash-safe snapshot of any map.
//!
//! Layout (all integers and floats little-endian):
//!
//! | bytes | content |
//! |---|---|
//! | 8 | magic `VLEMMAP\0` |
//! | 4 | format version (`u32`, currently 1) |
//! | 4 | header length `H` (`u32`) |
//! | H | header, UTF-8 JSON: map kind, point count, dimension, encoder config, provenance |
//! | 12·n | positions, `f32` x, y, z per point (map frame, metres) |
//! | 3·n | colours, `u8` r, g, b per point |
//! | 4·n·d | embeddings, `f32`, one unit-norm row per point |
//! | 4 | CRC-32 (IEEE) of every byte before it |
//!
//! Writing goes to a temporary file in the same directory, which is synced and then renamed over
//! the target, so a crash leaves either the old file or the new one, never a torn one. The
//! temporary file's name is unique (process id, a per-process counter and the clock) and it is
//! created exclusively (`O_EXCL`), so concurrent saves to one path, from threads or processes,
//! never write into each other's temporary file; a temporary file left behind by a killed save is
//! never reused. The last complete save wins the rename.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::config::StageConfig;
use crate::error::{CoreError, Result};

/// First bytes of every map file.
pub const MAGIC: &[u8; 8] = b"VLEMMAP\0";
/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
const PREFIX_LEN: usize = 16;

/// Where a map came from, stored in the file header.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
pub struct MapMetadata {
    /// The encoder that made the embeddings (so `vlem query` can embed text the same way).
    pub encoder: Option<StageConfig>,
    /// Directory the encoder's relative paths are resolved against.
    pub config_dir: Option<PathBuf>,
    /// Frames integrated into the map.
    pub frames_integrated: usize,
    /// Version of vlem that wrote the file.
    pub vlem_version: String,
}

/// Every element of a map as point, colour and embedding.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapSnapshot {
    /// Registered name of the map that produced it.
    pub map_kind: String,
    /// Embedding dimension (0: geometry only).
    pub dim: usize,
    /// Positions in the map frame, metres.
    pub positions: Vec<[f32; 3]>,
    /// RGB colours.
    pub colours: Vec<[u8; 3]>,
    /// Row-major `len x dim` unit-norm embeddings.
    pub embeddings: Vec<f32>,
    /// Provenance.
    pub metadata: MapMetadata,
}

impl MapSnapshot {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Checks that the arrays agree in length.
    ///
    /// # Errors
    /// [`CoreError::DimensionMismatch`] naming the array that disagrees.
    pub fn validate(&self) -> Result<()> {
        let n = self.positions.len();
        if self.colours.len() != n {
            return Err(CoreError::DimensionMismatch {
                what: "snapshot colours (count)".into(),
                expected: n,
                actual: self.colours.len(),
            });
        }
        if self.embeddings.len() != n * self.dim {
            return Err(CoreError::DimensionMismatch {
                what: "snapshot embeddings (values)".into(),
                expected: n * self.dim,
                actual: self.embeddings.len(),
            });
        }
        Ok(())
    }
}

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct Header {
    map_kind: String,
    points: u64,
    dim: u64,
    embedding_type: String,
    metadata: MapMetadata,
}

/// CRC-32 over everything written through it.
struct Checksummed<W: Write> {
    inner: W,
    crc: crc32fast::Hasher,
}

impl<W: Write> Write for Checksummed<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Writes `snapshot` to `path` atomically (temporary file, sync, rename). Returns the file size.
///
/// # Errors
/// [`CoreError::Io`] naming the file, or an inconsistent snapshot.
pub fn write_map_file(path: &Path, snapshot: &MapSnapshot) -> Result<u64> {
    snapshot.validate()?;
    crate::files::replace_file(path, "map.vlem", |tmp, file| write_to(tmp, file, snapshot))
}

fn write_to(tmp: &Path, file: File, snapshot: &MapSnapshot) -> Result<u64> {
    let io = |e| CoreError::io(tmp, e);
    let inner = encode_into(BufWriter::with_capacity(1 << 20, file), snapshot, tmp)?;
    let file = inner
        .into_inner()
        .map_err(|e| CoreError::io(tmp, e.into_error()))?;
    file.sync_all().map_err(io)?;
    Ok(file.metadata().map_err(io)?.len())
}

/// The bytes of the map file [`write_map_file`] would write for `snapshot`, e.g. to send it over
/// a network.
///
/// # Errors
/// An inconsistent snapshot, or a header that cannot be encoded.
pub fn map_file_bytes(snapshot: &MapSnapshot) -> Result<Vec<u8>> {
    snapshot.validate()?;
    let capacity = 64 + snapshot.len() * (15 + 4 * snapshot.dim);
    encode_into(
        Vec::with_capacity(capacity),
        snapshot,
        Path::new("(in memory)"),
    )
}

/// Streams the map file of `snapshot` into `writer` (a socket, a pipe) without building it in
/// memory first, and returns the writer; [`map_file_len`] says beforehand how many bytes come.
///
/// # Errors
/// An inconsistent snapshot, a header that cannot be encoded, or a failed write.
pub fn write_map_to<W: Write>(writer: W, snapshot: &MapSnapshot) -> Result<W> {
    snapshot.validate()?;
    encode_into(writer, snapshot, Path::new("(stream)"))
}

/// The size in bytes of the map file of `snapshot` (for a `Content-Length`).
///
/// # Errors
/// A header that cannot be encoded.
pub fn map_file_len(snapshot: &MapSnapshot) -> Result<u64> {
    let header = serde_json::to_vec(&header_of(snapshot)).map_err(|e| CoreError::MapFile {
        path: PathBuf::from("(stream)"),
        reason: format!("cannot encode header: {e}"),
    })?;
    let n = snapshot.len() as u64;
    Ok(PREFIX_LEN as u64 + header.len() as u64 + n * 15 + n * snapshot.dim as u64 * 4 + 4)
}

fn header_of(snapshot: &MapSnapshot) -> Header {
    Header {
        map_kind: snapshot.map_kind.clone(),
        points: snapshot.len() as u64,
        dim: snapshot.dim as u64,
        embedding_type: "f32".into(),
        metadata: snapshot.metadata.clone(),
    }
}

/// Writes the whole file format into `inner` (errors name `path`) and returns it.
fn encode_into<W: Write>(inner: W, snapshot: &MapSnapshot, path: &Path) -> Result<W> {
    let io = |e| CoreError::io(path, e);
    let header = serde_json::to_vec(&header_of(snapshot)).map_err(|e| CoreError::MapFile {
        path: path.to_path_buf(),
        reason: format!("cannot encode header: {e}"),
    })?;
    let header_len = u32::try_from(header.len()).map_err(|_| CoreError::MapFile {
        path: path.to_path_buf(),
        reason: "header larger than 4 GiB".into(),
    })?;
    let mut w = Checksummed {
        inner,
        crc: crc32fast::Hasher::new(),
    };
    w.write_all(MAGIC).map_err(io)?;
    w.write_all(&FORMAT_VERSION.to_le_bytes()).map_err(io)?;
    w.write_all(&header_len.to_le_bytes()).map_err(io)?;
    w.write_all(&header).map_err(io)?;
    let mut buf = Vec::with_capacity(1 << 16);
    for chunk in snapshot.positions.chunks(4096) {
        buf.clear();
        chunk
            .iter()
            .flatten()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes()));
        w.write_all(&buf).map_err(io)?;
    }
    for chunk in snapshot.colours.chunks(1 << 14) {
        buf.clear();
        chunk.iter().for_each(|c| buf.extend_from_slice(c));
        w.write_all(&buf).map_err(io)?;
    }
    for chunk in snapshot.embeddings.chunks(1 << 14) {
        buf.clear();
        chunk
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes()));
        w.write_all(&buf).map_err(io)?;
    }
    let crc = w.crc.clone().finalize();
    let mut inner = w.inner;
    inner.write_all(&crc.to_le_bytes()).map_err(io)?;
    Ok(inner)
}

/// Reads a map file written by [`write_map_file`].
///
/// # Errors
/// [`CoreError::Io`] when unreadable, and those of [`map_file_from_bytes`].
pub fn read_map_file(path: &Path) -> Result<MapSnapshot> {
    use std::io::Read;
    let io = |e| CoreError::io(path, e);
    let file = std::fs::File::open(path).map_err(io)?;
    // Only a regular file has a size to trust: a stream or device (`/dev/zero`, a pipe) would be
    // read until memory runs out.
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(CoreError::MapFile {
            path: path.to_path_buf(),
            reason: "not a regular file (a folder, device, pipe or socket): map files are read \
                     from regular files only"
                .into(),
        });
    }
    let len = meta.len();
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    // No more than the size said when the file was opened (plus one byte to notice growth).
    file.take(len.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    map_file_from_bytes(&bytes, path)
}

/// Parses the bytes of a map file written by [`write_map_file`]; `path` is the file they came
/// from, as errors name it. Nothing is allocated beyond what the bytes hold: the point count and
/// dimension of the header must match the length of the bytes before any array is built.
///
/// # Errors
/// [`CoreError::MapFile`] for a foreign file (bad magic), a newer format version, a truncated or
/// over-long file, a checksum mismatch or a malformed header.
pub fn map_file_from_bytes(bytes: &[u8], path: &Path) -> Result<MapSnapshot> {
    let fail = |reason: String| CoreError::MapFile {
        path: path.to_path_buf(),
        reason,
    };
    if bytes.len() < MAGIC.len() && MAGIC.starts_with(bytes) {
        return Err(fail(format!(
            "truncated: {} bytes, shorter than the file prefix",
            bytes.len()
        )));
    }
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err(fail("not a vlem map file (wrong magic bytes)".into()));
    }
    if bytes.len() < PREFIX_LEN {
        return Err(fail(format!(
            "truncated: {} bytes, shorter than the file prefix",
            bytes.len()
        )));
    }
    let word =
        |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    // Whether the trailing CRC matches: a prefix field that reads wrong in a file that fails it
    // is corruption, reported as such rather than as what the damaged field seems to say.
    let intact = bytes.len() >= PREFIX_LEN + 4 && {
        let end = bytes.len() - 4;
        word(end) == crc32fast::hash(&bytes[..end])
    };
    let corrupted = |field: &str| {
        fail(format!(
            "checksum mismatch with an unreadable {field}: the file is corrupted or truncated"
        ))
    };
    let version = word(8);
    if version != FORMAT_VERSION {
        if !intact {
            return Err(corrupted(&format!("format version ({version})")));
        }
        return Err(fail(format!(
            "format version {version}, this build of vlem reads version {FORMAT_VERSION}"
        )));
    }
    let header_len = word(12) as usize;
    let header_end = PREFIX_LEN + header_len;
    if bytes.len() < header_end + 4 {
        return Err(fail(format!(
            "truncated: {} bytes, the header alone needs {}",
            bytes.len(),
            header_end + 4
        )));
    }
    let header: Header = match serde_json::from_slice(&bytes[PREFIX_LEN..header_end]) {
        Ok(header) => header,
        Err(_) if !intact => return Err(corrupted("header")),
        Err(e) => return Err(fail(format!("malformed header: {e}"))),
    };
    if header.embedding_type != "f32" {
        if !intact {
            return Err(corrupted("header"));
        }
        return Err(fail(format!(
            "unknown embedding type `{}`",
            header.embedding_type
        )));
    }
    let n = usize::try_from(header.points).map_err(|_| fail("point count overflows".into()))?;
    let dim = usize::try_from(header.dim).map_err(|_| fail("dimension overflows".into()))?;
    // Header, payload (positions, colours, embeddings) and CRC.
    let expected = n
        .checked_mul(12 + 3)
        .and_then(|a| n.checked_mul(dim)?.checked_mul(4)?.checked_add(a))
        .and_then(|payload| payload.checked_add(header_end + 4))
        .ok_or_else(|| fail("point count and dimension overflow".into()))?;
    if bytes.len() != expected {
        let what = if bytes.len() < expected {
            "truncated"
        } else {
            "trailing bytes"
        };
        return Err(fail(format!(
            "{what}: {} bytes, {n} points of dimension {dim} need {expected}",
            bytes.len()
        )));
    }
    let stored = word(expected - 4);
    let actual = crc32fast::hash(&bytes[..expected - 4]);
    if stored != actual {
        return Err(fail(format!(
            "checksum mismatch (stored {stored:08x}, computed {actual:08x}): the file is corrupted"
        )));
    }
    let f32_at =
        |at: usize| f32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let mut at = header_end;
    let positions: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            let p = at + i * 12;
            [f32_at(p), f32_at(p + 4), f32_at(p + 8)]
        })
        .collect();
    at += n * 12;
    let colours = bytes[at..at + n * 3]
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    at += n * 3;
    let embeddings: Vec<f32> = bytes[at..at + n * dim * 4]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    // A valid checksum over NaN or infinite values (written by a broken producer) still makes a
    // map that answers every query with NaN: refused, naming the first bad row.
    let bad_position = positions
        .iter()
        .position(|p: &[f32; 3]| !p.iter().all(|v| v.is_finite()));
    let bad_embedding = (dim > 0)
        .then(|| {
            embeddings
                .chunks_exact(dim)
                .position(|row| !row.iter().all(|v| v.is_finite()))
        })
        .flatten();
    if let Some(row) = bad_position {
        return Err(fail(format!(
            "point {row} has a position that is not finite (NaN or infinite)"
        )));
    }
    if let Some(row) = bad_embedding {
        return Err(fail(format!(
            "point {row} has an embedding value that is not finite (NaN or infinite)"
        )));
    }
    Ok(MapSnapshot {
        map_kind: header.map_kind,
        dim,
        positions,
        colours,
        embeddings,
        metadata: header.metadata,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_streamed_map_file_is_the_file_and_its_length_is_known_beforehand() {
        let snapshot = MapSnapshot {
            map_kind: "voxel".into(),
            dim: 2,
            positions: vec![[0.0, 1.0, 2.0], [1.0, 1.0, 1.0]],
            colours: vec![[1, 2, 3]; 2],
            embeddings: vec![1.0, 0.0, 0.6, 0.8],
            metadata: MapMetadata::default(),
        };
        let streamed = write_map_to(Vec::new(), &snapshot).unwrap();
        assert_eq!(streamed, map_file_bytes(&snapshot).unwrap());
        assert_eq!(map_file_len(&snapshot).unwrap(), streamed.len() as u64);
    }

    #[test]
    fn non_finite_values_and_special_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.vlem");
        let good = MapSnapshot {
            map_kind: "point-cloud".into(),
            dim: 2,
            positions: vec![[0.0, 1.0, 2.0], [1.0, 1.0, 1.0], [2.0, 0.0, 1.0]],
            colours: vec![[1, 2, 3]; 3],
            embeddings: vec![1.0, 0.0, 0.6, 0.8, 0.0, 1.0],
            metadata: MapMetadata::default(),
        };
        write_map_file(&path, &good).unwrap();
        assert_eq!(read_map_file(&path).unwrap().len(), 3);
        let mut nan_position = good.clone();
        nan_position.positions[1][2] = f32::NAN;
        write_map_file(&path, &nan_position).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.ends_with("point 1 has a position that is not finite (NaN or infinite)"),
            "{err}"
        );
        let mut infinite = good.clone();
        infinite.embeddings[5] = f32::INFINITY;
        write_map_file(&path, &infinite).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("point 2 has an embedding value that is not finite"),
            "{err}"
        );
        let err = read_map_file(dir.path()).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        if Path::new("/dev/zero").exists() {
            let err = read_map_file(Path::new("/dev/zero"))
                .unwrap_err()
                .to_string();
            assert!(err.contains("not a regular file"), "{err}");
        }
    }

    fn sample() -> MapSnapshot {
        MapSnapshot {
            map_kind: "point-cloud".into(),
            dim: 2,
            positions: vec![[0.0, 1.0, 2.0], [-1.5, 0.25, 3.0]],
            colours: vec![[255, 0, 0], [1, 2, 3]],
            embeddings: vec![1.0, 0.0, 0.6, 0.8],
            metadata: MapMetadata {
                encoder: Some(StageConfig::named("colour-names")),
                config_dir: Some("/tmp".into()),
                frames_integrated: 5,
                vlem_version: "0.1.0".into(),
            },
        }
    }

    #[test]
    fn round_trip_is_lossless() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.vlem");
        let size = write_map_file(&path, &sample()).unwrap();
        assert_eq!(size, std::fs::metadata(&path).unwrap().len());
        assert_eq!(read_map_file(&path).unwrap(), sample());
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn truncated_corrupted_and_foreign_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.vlem");
        write_map_file(&path, &sample()).unwrap();
        let good = std::fs::read(&path).unwrap();

        std::fs::write(&path, &good[..good.len() - 10]).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
        assert!(err.contains("2 points of dimension 2"), "{err}");

        let mut bad = good.clone();
        let last_value = bad.len() - 6;
        bad[last_value] ^= 0x40;
        std::fs::write(&path, &bad).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(err.contains("checksum mismatch"), "{err}");
        assert!(err.contains("corrupted"), "{err}");

        std::fs::write(&path, b"PK\x03\x04 definitely a zip file").unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.ends_with("not a vlem map file (wrong magic bytes)"),
            "{err}"
        );

        // A file of a newer format (intact: its checksum matches) names the version...
        let mut newer = good.clone();
        newer[8] = 9;
        let end = newer.len() - 4;
        let crc = crc32fast::hash(&newer[..end]);
        newer[end..].copy_from_slice(&crc.to_le_bytes());
        std::fs::write(&path, &newer).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("format version 9, this build of vlem reads version 1"),
            "{err}"
        );
        // ...a damaged version field or header is corruption, not a newer format.
        let mut damaged = good.clone();
        damaged[8] = 9;
        std::fs::write(&path, &damaged).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("checksum mismatch") && err.contains("corrupted"),
            "{err}"
        );
        let mut damaged = good.clone();
        damaged[PREFIX_LEN] = b'[';
        std::fs::write(&path, &damaged).unwrap();
        let err = read_map_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("checksum mismatch with an unreadable header"),
            "{err}"
        );

        // A file cut inside the magic bytes (or empty) is truncated, not foreign.
        for cut in [0, 5] {
            std::fs::write(&path, &good[..cut]).unwrap();
            let err = read_map_file(&path).unwrap_err().to_string();
            assert!(err.contains(&format!("truncated: {cut} bytes")), "{err}");
        }
    }

    #[test]
    fn concurrent_saves_in_one_process_use_distinct_temporary_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.vlem");
        std::thread::scope(|s| {
            for _ in 0..4 {
                s.spawn(|| {
                    for _ in 0..25 {
                        write_map_file(&path, &sample()).unwrap();
                    }
                });
            }
        });
        assert_eq!(read_map_file(&path).unwrap(), sample());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_leftover_temporary_file_is_neither_reused_nor_an_obstacle() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.vlem");
        // What a save killed in this process (same pid) would have left.
        let (tmp, _file) = crate::files::create_temp_file(dir.path(), "map.vlem").unwrap();
        std::fs::write(&tmp, b"half a map").unwrap();
        write_map_file(&path, &sample()).unwrap();
        assert_eq!(read_map_file(&path).unwrap(), sample());
        assert_eq!(std::fs::read(&tmp).unwrap(), b"half a map");
    }

    #[test]
    fn failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.vlem");
        write_map_file(&path, &sample()).unwrap();
        let mut broken = sample();
        broken.embeddings.pop();
        assert!(write_map_file(&path, &broken).is_err());
        assert_eq!(read_map_file(&path).unwrap(), sample());
    }
}
