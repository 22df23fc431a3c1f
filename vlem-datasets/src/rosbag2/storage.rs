//! The two storage formats of rosbag2, behind one interface: list the topics, scan the messages
//! once, fetch a message again by where the scan saw it.
//!
//! Why both and why this shape: `ros2 bag record` writes MCAP since Iron and SQLite3 (`.db3`)
//! before, and users have both. A bag of raw 640×480 frames grows by ~50 MB a second, so the
//! reader never holds the images: opening scans every message once (decoding only the stamps of
//! the image topics), and a frame fetches its two images again. SQLite fetches by row id. MCAP
//! messages may sit in compressed chunks that no file offset addresses, so an MCAP file is read
//! forward with one cursor kept between fetches: frames read in order (as the pipeline reads them)
//! cost one pass over the file in all, and going back restarts the pass from the start.

use std::collections::HashMap;
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

use crate::error::{DatasetError, Result};

/// A topic of the bag: its name, message type and message count (over every storage file).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopicInfo {
    /// Topic name, e.g. `/camera/color/image_raw`.
    pub name: String,
    /// Message type as the bag records it, e.g. `sensor_msgs/msg/Image`.
    pub type_name: String,
    /// Messages on the topic.
    pub count: u64,
}

/// Where the scan saw a message, to fetch it again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct MessageKey {
    /// Storage file, in the bag's order.
    file: usize,
    /// MCAP: the message's position among the file's messages; SQLite: its row id.
    position: u64,
}

/// What [`Bag::scan`] calls for each wanted message: its topic, where it is, its CDR data.
pub type Visitor<'a> = dyn FnMut(&TopicInfo, MessageKey, &[u8]) -> Result<()> + 'a;

/// An open bag: its storage files, in order.
pub struct Bag {
    path: PathBuf,
    files: Vec<StorageFile>,
}

enum StorageFile {
    Mcap(McapFile),
    Sqlite(SqliteFile),
}

impl Bag {
    /// Opens a rosbag2 folder (every `.mcap` or `.db3` file in it, in split order) or one storage
    /// file.
    ///
    /// # Errors
    /// [`DatasetError::Bag`] for a folder without storage files, a bag compressed by rosbag2
    /// (`--compression-mode`), or a file that is neither MCAP nor SQLite3.
    pub fn open(path: &Path) -> Result<Self> {
        let paths = storage_files(path)?;
        let files = paths
            .into_iter()
            .map(|file| {
                if is_sqlite(&file) {
                    SqliteFile::open(&file).map(StorageFile::Sqlite)
                } else {
                    Ok(StorageFile::Mcap(McapFile::open(&file)?))
                }
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            path: path.to_path_buf(),
            files,
        })
    }

    /// The path the bag was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads every message once, in each file's order: `visit(topic, key, data)` is called for the
    /// messages of the topics `wanted` accepts. Returns every topic of the bag with its type and
    /// message count.
    ///
    /// # Errors
    /// [`DatasetError::Bag`] for a storage file that cannot be read, and whatever `visit` returns.
    pub fn scan(
        &mut self,
        wanted: &dyn Fn(&str) -> bool,
        visit: &mut Visitor<'_>,
    ) -> Result<Vec<TopicInfo>> {
        let mut topics: Vec<TopicInfo> = Vec::new();
        for (index, file) in self.files.iter_mut().enumerate() {
            let found = match file {
                StorageFile::Mcap(f) => f.scan(index, wanted, visit)?,
                StorageFile::Sqlite(f) => f.scan(index, wanted, visit)?,
            };
            for topic in found {
                match topics.iter_mut().find(|t| t.name == topic.name) {
                    Some(t) => t.count += topic.count,
                    None => topics.push(topic),
                }
            }
        }
        topics.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(topics)
    }

    /// The data of the messages at `keys`, in the order given. Fetching in the order of the scan
    /// is fastest (see the module docs).
    ///
    /// # Errors
    /// [`DatasetError::Bag`] for a storage file that cannot be read or a key no scan gave.
    pub fn fetch(&mut self, keys: &[MessageKey]) -> Result<Vec<Vec<u8>>> {
        let mut order: Vec<usize> = (0..keys.len()).collect();
        order.sort_by_key(|&i| keys[i]);
        let mut out = vec![Vec::new(); keys.len()];
        for i in order {
            let key = keys[i];
            let file = self
                .files
                .get_mut(key.file)
                .ok_or_else(|| DatasetError::Bag {
                    path: self.path.clone(),
                    message: format!("no storage file {} in the bag", key.file),
                })?;
            out[i] = match file {
                StorageFile::Mcap(f) => f.fetch(key.position)?,
                StorageFile::Sqlite(f) => f.fetch(key.position)?,
            };
        }
        Ok(out)
    }
}

fn is_sqlite(path: &Path) -> bool {
    let mut magic = [0u8; 16];
    File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok_and(|()| &magic == b"SQLite format 3\0")
}

/// The storage files of `path`: itself for a file, else the folder's `.mcap` / `.db3` files in
/// split order (`name_0`, `name_1`, …, `name_10`).
fn storage_files(path: &Path) -> Result<Vec<PathBuf>> {
    let bad = |message: String| DatasetError::Bag {
        path: path.to_path_buf(),
        message,
    };
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let entries = std::fs::read_dir(path).map_err(|e| DatasetError::io(path, e))?;
    let mut files = Vec::new();
    let mut compressed = Vec::new();
    let mut names = Vec::new();
    for entry in entries.flatten() {
        let file = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.ends_with(".mcap") || name.ends_with(".db3") {
            files.push(file);
        } else if name.ends_with(".zstd") {
            compressed.push(name.clone());
        }
        names.push(name);
    }
    let metadata = std::fs::read_to_string(path.join("metadata.yaml")).unwrap_or_default();
    let message_compression = metadata.lines().any(|line| {
        let line = line.trim();
        line.starts_with("compression_mode:") && line.to_ascii_uppercase().contains("MESSAGE")
    });
    if !compressed.is_empty() || message_compression {
        return Err(bad(format!(
            "the bag is compressed by rosbag2 ({}); vlem reads uncompressed bags: convert it \
             with `ros2 bag decompress` or `ros2 bag convert` (chunk compression inside MCAP \
             files is fine)",
            if compressed.is_empty() {
                "compression_mode MESSAGE in metadata.yaml".to_owned()
            } else {
                compressed.join(", ")
            }
        )));
    }
    if files.is_empty() {
        names.sort();
        return Err(bad(format!(
            "no .mcap or .db3 storage file in the folder (found: {})",
            if names.is_empty() {
                "nothing".to_owned()
            } else {
                names.join(", ")
            }
        )));
    }
    files.sort_by_key(|f| split_order(f));
    Ok(files)
}

/// Sort key of a split storage file: the name without its split number, then the number.
fn split_order(path: &Path) -> (String, u64, String) {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    match stem.rsplit_once('_') {
        Some((base, number)) if number.parse::<u64>().is_ok() => {
            (base.to_owned(), number.parse().unwrap_or(0), stem.clone())
        }
        _ => (stem.clone(), 0, stem),
    }
}

/// Most bytes handed to the MCAP reader at once.
const READ_BLOCK: usize = 1 << 20;

/// One MCAP file and the forward cursor fetches use.
struct McapFile {
    path: PathBuf,
    cursor: Option<McapCursor>,
}

/// A reader positioned after the message at `next - 1`.
struct McapCursor {
    file: File,
    reader: LinearReader,
    next: u64,
}

impl McapFile {
    fn open(path: &Path) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
        let mut magic = [0u8; 8];
        let is_mcap = file.read_exact(&mut magic).is_ok() && magic == *mcap::MAGIC;
        if !is_mcap {
            return Err(DatasetError::Bag {
                path: path.to_path_buf(),
                message: "neither an MCAP nor an SQLite3 file (rosbag2 storage is one of the two)"
                    .to_owned(),
            });
        }
        Ok(Self {
            path: path.to_path_buf(),
            cursor: None,
        })
    }

    fn error(&self, e: impl std::fmt::Display) -> DatasetError {
        DatasetError::Bag {
            path: self.path.clone(),
            message: format!("cannot read MCAP: {e}"),
        }
    }

    fn new_cursor(&self) -> Result<McapCursor> {
        let file = File::open(&self.path).map_err(|e| DatasetError::io(&self.path, e))?;
        let size = file
            .metadata()
            .map_err(|e| DatasetError::io(&self.path, e))?
            .len();
        // A record cannot be much larger than the file (chunks may compress it several times):
        // the limit keeps a corrupt length from allocating without bound.
        let limit = usize::try_from(size.saturating_mul(16))
            .unwrap_or(usize::MAX)
            .clamp(1 << 20, 1 << 32);
        let reader = LinearReader::new_with_options(
            LinearReaderOptions::default().with_record_length_limit(limit),
        );
        Ok(McapCursor {
            file,
            reader,
            next: 0,
        })
    }

    /// Reads records until the next message; `on_record` sees every record before it.
    fn next_message(
        &self,
        cursor: &mut McapCursor,
        on_record: &mut dyn FnMut(Record<'_>) -> Result<()>,
    ) -> Result<Option<(u16, Vec<u8>)>> {
        while let Some(event) = cursor.reader.next_event() {
            match event.map_err(|e| self.error(e))? {
                LinearReadEvent::ReadRequest(need) => {
                    // The request is a hint that a corrupt length can make huge (the fuzzer found
                    // 3.7 GB for a 5.6 kB file): feed at most 1 MiB at a time, and the reader
                    // asks again for the rest, or meets the end of the file.
                    let read = cursor
                        .file
                        .read(cursor.reader.insert(need.min(READ_BLOCK)))
                        .map_err(|e| DatasetError::io(&self.path, e))?;
                    cursor.reader.notify_read(read);
                }
                LinearReadEvent::Record { opcode, data } => {
                    let record = mcap::parse_record(opcode, data).map_err(|e| self.error(e))?;
                    if let Record::Message { header, data } = record {
                        cursor.next += 1;
                        return Ok(Some((header.channel_id, data.into_owned())));
                    }
                    on_record(record)?;
                }
            }
        }
        Ok(None)
    }

    fn scan(
        &mut self,
        file_index: usize,
        wanted: &dyn Fn(&str) -> bool,
        visit: &mut Visitor<'_>,
    ) -> Result<Vec<TopicInfo>> {
        let mut cursor = self.new_cursor()?;
        let mut schemas: HashMap<u16, String> = HashMap::new();
        // Channel id -> (topic, whether wanted).
        let mut channels: HashMap<u16, (TopicInfo, bool)> = HashMap::new();
        let mut pending: Vec<(u16, u16, String)> = Vec::new();
        loop {
            let mut on_record = |record: Record<'_>| -> Result<()> {
                match record {
                    Record::Schema { header, .. } => {
                        schemas.insert(header.id, header.name);
                    }
                    Record::Channel(channel) => {
                        pending.push((channel.id, channel.schema_id, channel.topic));
                    }
                    _ => {}
                }
                Ok(())
            };
            let message = self.next_message(&mut cursor, &mut on_record)?;
            // Channels refer to schemas that come before them; resolve them once both are known.
            for (id, schema_id, topic) in pending.drain(..) {
                let type_name = schemas.get(&schema_id).cloned().unwrap_or_default();
                let take = wanted(&topic);
                channels.entry(id).or_insert((
                    TopicInfo {
                        name: topic,
                        type_name,
                        count: 0,
                    },
                    take,
                ));
            }
            let Some((channel_id, data)) = message else {
                break;
            };
            let position = cursor.next - 1;
            let Some((topic, take)) = channels.get_mut(&channel_id) else {
                return Err(self.error(format!(
                    "message {position} is on channel {channel_id}, which no channel record defines"
                )));
            };
            topic.count += 1;
            if *take {
                let key = MessageKey {
                    file: file_index,
                    position,
                };
                visit(topic, key, &data)?;
            }
        }
        let mut topics: Vec<TopicInfo> = channels.into_values().map(|(t, _)| t).collect();
        topics.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(topics)
    }

    fn fetch(&mut self, position: u64) -> Result<Vec<u8>> {
        let mut cursor = match self.cursor.take() {
            Some(cursor) if cursor.next <= position => cursor,
            _ => self.new_cursor()?,
        };
        loop {
            let message = self.next_message(&mut cursor, &mut |_| Ok(()))?;
            let Some((_, data)) = message else {
                return Err(self.error(format!(
                    "message {position} is past the end of the file (it changed since it was opened?)"
                )));
            };
            if cursor.next == position + 1 {
                self.cursor = Some(cursor);
                return Ok(data);
            }
        }
    }
}

/// One SQLite3 storage file (`.db3`): tables `topics` and `messages`.
struct SqliteFile {
    path: PathBuf,
    connection: rusqlite::Connection,
}

impl SqliteFile {
    fn open(path: &Path) -> Result<Self> {
        let connection = rusqlite::Connection::open_with_flags(
            path,
            rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY | rusqlite::OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(|e| DatasetError::Bag {
            path: path.to_path_buf(),
            message: format!("cannot open SQLite3: {e}"),
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            connection,
        })
    }

    fn error(&self, e: impl std::fmt::Display) -> DatasetError {
        DatasetError::Bag {
            path: self.path.clone(),
            message: format!("cannot read the rosbag2 SQLite3 tables (topics, messages): {e}"),
        }
    }

    fn scan(
        &mut self,
        file_index: usize,
        wanted: &dyn Fn(&str) -> bool,
        visit: &mut Visitor<'_>,
    ) -> Result<Vec<TopicInfo>> {
        let mut topics: HashMap<i64, (TopicInfo, bool)> = HashMap::new();
        {
            let mut statement = self
                .connection
                .prepare("SELECT id, name, type FROM topics")
                .map_err(|e| self.error(e))?;
            let mut rows = statement.query([]).map_err(|e| self.error(e))?;
            while let Some(row) = rows.next().map_err(|e| self.error(e))? {
                let id: i64 = row.get(0).map_err(|e| self.error(e))?;
                let name: String = row.get(1).map_err(|e| self.error(e))?;
                let type_name: String = row.get(2).map_err(|e| self.error(e))?;
                let take = wanted(&name);
                let topic = TopicInfo {
                    name,
                    type_name,
                    count: 0,
                };
                topics.insert(id, (topic, take));
            }
        }
        {
            let mut statement = self
                .connection
                .prepare("SELECT id, topic_id, data FROM messages ORDER BY timestamp, id")
                .map_err(|e| self.error(e))?;
            let mut rows = statement.query([]).map_err(|e| self.error(e))?;
            while let Some(row) = rows.next().map_err(|e| self.error(e))? {
                let id: i64 = row.get(0).map_err(|e| self.error(e))?;
                let topic_id: i64 = row.get(1).map_err(|e| self.error(e))?;
                let Some((topic, take)) = topics.get_mut(&topic_id) else {
                    return Err(self.error(format!(
                        "message {id} is on topic id {topic_id}, which the topics table lacks"
                    )));
                };
                topic.count += 1;
                if *take {
                    let data = row.get_ref(2).map_err(|e| self.error(e))?;
                    let data = data.as_blob().map_err(|e| self.error(e))?;
                    let key = MessageKey {
                        file: file_index,
                        position: id.cast_unsigned(),
                    };
                    visit(topic, key, data)?;
                }
            }
        }
        let mut list: Vec<TopicInfo> = topics.into_values().map(|(t, _)| t).collect();
        list.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(list)
    }

    fn fetch(&mut self, position: u64) -> Result<Vec<u8>> {
        self.connection
            .query_row(
                "SELECT data FROM messages WHERE id = ?1",
                [position.cast_signed()],
                |row| row.get::<_, Vec<u8>>(0),
            )
            .map_err(|e| self.error(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_files_sort_by_number() {
        let mut files: Vec<PathBuf> = ["b_10.mcap", "b_2.mcap", "b_0.mcap", "b_1.mcap"]
            .iter()
            .map(PathBuf::from)
            .collect();
        files.sort_by_key(|f| split_order(f));
        let names: Vec<_> = files.iter().map(|f| f.to_string_lossy()).collect();
        assert_eq!(names, ["b_0.mcap", "b_1.mcap", "b_2.mcap", "b_10.mcap"]);
    }

    #[test]
    fn folders_without_storage_or_compressed_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("notes.txt"), "x").unwrap();
        let err = Bag::open(dir.path()).err().unwrap().to_string();
        assert!(
            err.contains("no .mcap or .db3") && err.contains("notes.txt"),
            "{err}"
        );
        std::fs::write(dir.path().join("b_0.mcap.zstd"), "x").unwrap();
        let err = Bag::open(dir.path()).err().unwrap().to_string();
        assert!(err.contains("ros2 bag decompress"), "{err}");
        let file = dir.path().join("notes.txt");
        let err = Bag::open(&file).err().unwrap().to_string();
        assert!(err.contains("neither an MCAP nor an SQLite3"), "{err}");
    }
}
