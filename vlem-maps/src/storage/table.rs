//! [`Table`]: a map's embeddings in host memory ([`EmbeddingStore`]) or on a device
//! ([`DeviceTable`], feature `candle`), chosen by `[map] device`.
//!
//! Why it exists: a map that can keep its table on a GPU still runs its geometry on the host;
//! the operations both tables share (length, memory, truncation, snapshots, queries) are written
//! here once, and the map branches only where the work itself differs (fusion, insertion,
//! merges: row by row on the host, as batched tensor operations on a device).

use vlem_backends::ComputeDevice;
use vlem_core::{CoreError, StageKind};

#[cfg(feature = "candle")]
use super::DeviceTable;
use super::{EmbeddingStore, Precision};
use crate::error::MapError;

/// A map's embedding table, on the host or on a device (not `Clone`, as the device table is not).
#[derive(Debug)]
pub(crate) enum Table {
    /// Host memory (`device = "cpu"`, and every geometry-only map).
    Host(EmbeddingStore),
    /// A candle device.
    #[cfg(feature = "candle")]
    Device(DeviceTable),
}

impl Table {
    /// The table of map `map` for `dim`-d embeddings on `device`, with room for `capacity` rows
    /// on a device (allocated now). A geometry-only map (`dim` 0) stays on the host.
    ///
    /// # Errors
    /// A stage error naming `map` when the device cannot be opened (a build without `cuda`, no
    /// driver, no such GPU) or cannot hold the table. Never a silent fall back to the host.
    pub(crate) fn open(
        map: &str,
        device: ComputeDevice,
        dim: usize,
        precision: Precision,
        capacity: usize,
    ) -> Result<Self, CoreError> {
        if device == ComputeDevice::Cpu || dim == 0 {
            return Ok(Self::Host(EmbeddingStore::new(dim, precision)));
        }
        Self::open_device(device, dim, precision, capacity)
            .map_err(|e| e.into_core(StageKind::Map, map))
    }

    /// The table of map `map` on the candle device `device` whatever the config names (how the
    /// tests run the device table on candle's CPU); a geometry-only map stays on the host.
    ///
    /// # Errors
    /// A stage error naming `map` when the device cannot hold the table.
    #[cfg(feature = "candle")]
    pub(crate) fn on_candle(
        map: &str,
        device: &candle_core::Device,
        dim: usize,
        precision: Precision,
        capacity: usize,
    ) -> Result<Self, CoreError> {
        if dim == 0 {
            return Ok(Self::Host(EmbeddingStore::new(dim, precision)));
        }
        DeviceTable::new(device, dim, precision, capacity)
            .map(Self::Device)
            .map_err(|e| e.into_core(StageKind::Map, map))
    }

    #[cfg(feature = "candle")]
    fn open_device(
        device: ComputeDevice,
        dim: usize,
        precision: Precision,
        capacity: usize,
    ) -> Result<Self, MapError> {
        let opened = device.open()?;
        Ok(Self::Device(DeviceTable::new(
            &opened, dim, precision, capacity,
        )?))
    }

    #[cfg(not(feature = "candle"))]
    fn open_device(
        device: ComputeDevice,
        _dim: usize,
        _precision: Precision,
        _capacity: usize,
    ) -> Result<Self, MapError> {
        Err(device.not_in_this_build().into())
    }

    /// The host table, `None` on a device.
    pub(crate) fn host_mut(&mut self) -> Option<&mut EmbeddingStore> {
        match self {
            Self::Host(t) => Some(t),
            #[cfg(feature = "candle")]
            Self::Device(_) => None,
        }
    }

    /// Host bytes of the values.
    pub(crate) fn host_bytes(&self) -> usize {
        match self {
            Self::Host(t) => t.memory_bytes(),
            #[cfg(feature = "candle")]
            Self::Device(_) => 0,
        }
    }

    /// Device bytes of the values.
    pub(crate) fn device_bytes(&self) -> usize {
        match self {
            Self::Host(_) => 0,
            #[cfg(feature = "candle")]
            Self::Device(t) => t.device_bytes(),
        }
    }

    /// Keeps the first `rows` rows (the point cloud's downsampling; the voxel map never shrinks).
    #[cfg(feature = "point-cloud")]
    pub(crate) fn truncate(&mut self, rows: usize) {
        match self {
            Self::Host(t) => t.truncate(rows),
            #[cfg(feature = "candle")]
            Self::Device(t) => t.truncate(rows),
        }
    }

    /// Every row widened to `f32`, on the host.
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy from the device fails.
    pub(crate) fn to_f32(&self) -> Result<Vec<f32>, MapError> {
        match self {
            Self::Host(t) => Ok(t.to_f32()),
            #[cfg(feature = "candle")]
            Self::Device(t) => t.to_f32(),
        }
    }

    /// Replaces every row by `values` (`rows × dim`).
    ///
    /// # Errors
    /// [`MapError::DeviceTable`] when the copy to the device fails.
    pub(crate) fn replace(&mut self, values: Vec<f32>) -> Result<(), MapError> {
        match self {
            Self::Host(t) => {
                *t = EmbeddingStore::from_f32(t.dim(), t.precision(), values);
                Ok(())
            }
            #[cfg(feature = "candle")]
            Self::Device(t) => t.replace(&values),
        }
    }

    /// [`EmbeddingStore::similarity_many`] on whichever table this is.
    ///
    /// # Errors
    /// As [`EmbeddingStore::similarity_many`]; a failed device operation as a stage error.
    pub(crate) fn similarity_many(
        &self,
        texts: &[&[f32]],
        out: &mut Vec<Vec<f32>>,
    ) -> vlem_core::Result<()> {
        match self {
            Self::Host(t) => t.similarity_many(texts, out),
            #[cfg(feature = "candle")]
            Self::Device(t) => t.similarity_many(texts, out),
        }
    }

    /// [`EmbeddingStore::similarity`] on whichever table this is.
    ///
    /// # Errors
    /// As [`EmbeddingStore::similarity`].
    pub(crate) fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> vlem_core::Result<()> {
        match self {
            Self::Host(t) => t.similarity(text, out),
            #[cfg(feature = "candle")]
            Self::Device(t) => {
                let mut scores = Vec::new();
                t.similarity_many(&[text], &mut scores)?;
                *out = scores.pop().unwrap_or_default();
                Ok(())
            }
        }
    }
}
