//! A reader of OMG CDR, the serialisation of every message in a ROS 2 bag.
//!
//! Why our own: the messages a bag holds for vlem are a handful of fixed ROS 2 types, and reading
//! them field by field needs only CDR's primitives (little- or big-endian numbers aligned to their
//! size from the start of the payload, strings and sequences with a 32-bit length). A serde-based
//! crate would add a dependency and still need the same per-type code. Every read is bounds-checked
//! and returns an error; nothing here can panic on a malformed or truncated message (the fuzz
//! target `rosbag2_messages` checks).

use std::fmt;

/// What is wrong with a CDR payload.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CdrError {
    /// Byte offset in the payload (after the 4-byte encapsulation header) where reading stopped.
    pub offset: usize,
    /// What was expected there.
    pub message: String,
}

impl fmt::Display for CdrError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "CDR byte {}: {}", self.offset, self.message)
    }
}

/// A cursor over one CDR-encoded message.
pub struct CdrReader<'a> {
    /// The payload after the encapsulation header; alignment is relative to its start.
    body: &'a [u8],
    position: usize,
    little_endian: bool,
}

/// Largest sequence length accepted before reading it: more elements than bytes left is a
/// corrupt length, and refusing it early keeps a fuzzed length from allocating gigabytes.
fn check_count(count: usize, element_size: usize, left: usize) -> bool {
    count.checked_mul(element_size).is_some_and(|n| n <= left)
}

impl<'a> CdrReader<'a> {
    /// Reads the 4-byte encapsulation header (`00 00` big-endian or `00 01` little-endian plain
    /// CDR, then two option bytes) and positions the cursor after it.
    ///
    /// # Errors
    /// A payload shorter than the header, or another representation (XCDR2, parameter lists).
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        let Some((header, body)) = data.split_first_chunk::<4>() else {
            return Err(CdrError {
                offset: 0,
                message: format!(
                    "{} bytes is shorter than the 4-byte encapsulation header",
                    data.len()
                ),
            });
        };
        let little_endian = match [header[0], header[1]] {
            [0, 0] => false,
            [0, 1] => true,
            other => {
                return Err(CdrError {
                    offset: 0,
                    message: format!(
                        "encapsulation {:02x}{:02x} is not plain CDR (00 00 or 00 01); \
                         ROS 2 bags write plain CDR",
                        other[0], other[1]
                    ),
                });
            }
        };
        Ok(Self {
            body,
            position: 0,
            little_endian,
        })
    }

    fn error(&self, message: impl Into<String>) -> CdrError {
        CdrError {
            offset: self.position,
            message: message.into(),
        }
    }

    /// Bytes left after the cursor.
    pub fn remaining(&self) -> usize {
        self.body.len().saturating_sub(self.position)
    }

    fn align(&mut self, size: usize) -> Result<(), CdrError> {
        let padding = (size - self.position % size) % size;
        if padding > self.remaining() {
            return Err(self.error(format!("truncated: {size}-byte alignment past the end")));
        }
        self.position += padding;
        Ok(())
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], CdrError> {
        if n > self.remaining() {
            return Err(self.error(format!(
                "truncated: {what} needs {n} bytes, {} left",
                self.remaining()
            )));
        }
        let bytes = &self.body[self.position..self.position + n];
        self.position += n;
        Ok(bytes)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], CdrError> {
        self.align(N)?;
        let bytes = self.take(N, what)?;
        let mut out = [0; N];
        out.copy_from_slice(bytes);
        if !self.little_endian {
            out.reverse();
        }
        Ok(out)
    }

    /// An `uint8` (also `bool`, `char`, `byte`).
    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.take(1, "a uint8")?[0])
    }

    /// A `uint32`.
    pub fn u32(&mut self) -> Result<u32, CdrError> {
        self.array::<4>("a uint32").map(u32::from_le_bytes)
    }

    /// An `int32`.
    pub fn i32(&mut self) -> Result<i32, CdrError> {
        self.array::<4>("an int32").map(i32::from_le_bytes)
    }

    /// A `float64`.
    pub fn f64(&mut self) -> Result<f64, CdrError> {
        self.array::<8>("a float64").map(f64::from_le_bytes)
    }

    /// A `string`: 32-bit length including the terminating NUL, the bytes, the NUL. Invalid UTF-8
    /// is replaced, as topic and frame names are only shown.
    pub fn string(&mut self) -> Result<String, CdrError> {
        let length = self.u32()? as usize;
        let bytes = self.take(length, "a string")?;
        // Some writers omit the NUL of an empty string (length 0); others always write it.
        let text = bytes.strip_suffix(&[0]).unwrap_or(bytes);
        Ok(String::from_utf8_lossy(text).into_owned())
    }

    /// A `uint8[]` sequence, borrowed from the message.
    pub fn bytes(&mut self) -> Result<&'a [u8], CdrError> {
        let count = self.u32()? as usize;
        self.take(count, "a uint8 sequence")
    }

    /// A `float64[]` sequence.
    pub fn f64_sequence(&mut self) -> Result<Vec<f64>, CdrError> {
        let count = self.u32()? as usize;
        if !check_count(count, 8, self.remaining()) {
            return Err(self.error(format!(
                "a float64 sequence of {count} elements is longer than the {} bytes left",
                self.remaining()
            )));
        }
        (0..count).map(|_| self.f64()).collect()
    }

    /// A `float64[N]` array.
    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        let mut out = [0.0; N];
        for value in &mut out {
            *value = self.f64()?;
        }
        Ok(out)
    }

    /// The length of a sequence of structs whose elements take at least `min_element_size`
    /// bytes each (so a corrupt length is refused before anything is allocated).
    pub fn sequence_length(&mut self, min_element_size: usize) -> Result<usize, CdrError> {
        let count = self.u32()? as usize;
        if !check_count(count, min_element_size.max(1), self.remaining()) {
            return Err(self.error(format!(
                "a sequence of {count} elements is longer than the {} bytes left",
                self.remaining()
            )));
        }
        Ok(count)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A little-endian payload written by hand: encapsulation, u8, padding, u32, string, f64.
    #[test]
    fn reads_aligned_primitives_in_both_byte_orders() {
        let mut le = vec![0, 1, 0, 0, 7, 0, 0, 0];
        le.extend(5u32.to_le_bytes());
        le.extend(3u32.to_le_bytes());
        le.extend(b"ab\0");
        le.push(0); // f64 alignment: body offset 15 -> 16
        le.extend(2.5f64.to_le_bytes());
        let mut r = CdrReader::new(&le).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.u32().unwrap(), 5);
        assert_eq!(r.string().unwrap(), "ab");
        assert_eq!(r.f64().unwrap(), 2.5);
        assert_eq!(r.remaining(), 0);

        let mut be = vec![0, 0, 0, 0, 7, 0, 0, 0];
        be.extend(5u32.to_be_bytes());
        be.extend(2.5f64.to_be_bytes());
        let mut r = CdrReader::new(&be).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.u32().unwrap(), 5);
        assert_eq!(r.f64().unwrap(), 2.5);
    }

    #[test]
    fn truncated_and_oversized_inputs_are_errors() {
        assert!(CdrReader::new(&[0, 1]).is_err());
        assert!(CdrReader::new(&[0, 7, 0, 0]).is_err());
        let mut r = CdrReader::new(&[0, 1, 0, 0, 1, 0]).unwrap();
        assert!(r.u32().is_err());
        // A sequence that claims more elements than there are bytes.
        let mut data = vec![0, 1, 0, 0];
        data.extend(u32::MAX.to_le_bytes());
        let mut r = CdrReader::new(&data).unwrap();
        assert!(r.f64_sequence().is_err());
        let mut r = CdrReader::new(&data).unwrap();
        assert!(r.bytes().is_err());
        let mut r = CdrReader::new(&data).unwrap();
        assert!(r.string().is_err());
    }
}
