//! The peak device memory of a run, as the driver reports it: what `stats.json` states beside the
//! peak resident memory, so a run can be compared with the paper's VRAM table row by row.
//!
//! Why sampling: candle allocates through the CUDA driver without a counter of its own, and the
//! tensors of a frame come and go between integrations. A thread asks the driver every 20 ms for the memory in use on each GPU the run opened and keeps the largest sum.
//! The driver's figure is the whole GPU's (every process, and the context itself), as
//! `nvidia-smi` shows it.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use super::ComputeDevice;

/// How often the driver is asked.
const SAMPLE_EVERY: Duration = Duration::from_millis(20);

/// A running sampler of the device memory in use; [`DeviceMemoryPeak::finish`] stops it.
#[derive(Debug)]
pub struct DeviceMemoryPeak {
    stop: Arc<AtomicBool>,
    peak: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
}

impl DeviceMemoryPeak {
    /// Starts sampling the GPUs among `devices`; `None` when there is none, in a build without
    /// `cuda`, or when the driver does not answer for them.
    pub fn start(devices: &[ComputeDevice]) -> Option<Self> {
        let mut gpus: Vec<usize> = devices
            .iter()
            .filter_map(|d| match d {
                ComputeDevice::Cuda(index) => Some(*index),
                ComputeDevice::Cpu => None,
            })
            .collect();
        gpus.sort_unstable();
        gpus.dedup();
        let gpus = Gpus::open(&gpus)?;
        let first = gpus.in_use()?;
        let stop = Arc::new(AtomicBool::new(false));
        let peak = Arc::new(AtomicU64::new(first));
        let thread = {
            let (stop, peak) = (Arc::clone(&stop), Arc::clone(&peak));
            std::thread::Builder::new()
                .name("vlem-device-memory".into())
                .spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        if let Some(bytes) = gpus.in_use() {
                            peak.fetch_max(bytes, Ordering::Relaxed);
                        }
                        std::thread::sleep(SAMPLE_EVERY);
                    }
                })
                .ok()?
        };
        Some(Self {
            stop,
            peak,
            thread: Some(thread),
        })
    }

    /// The largest device memory in use seen so far, in bytes.
    pub fn peak(&self) -> u64 {
        self.peak.load(Ordering::Relaxed)
    }

    /// Stops sampling; returns the peak.
    pub fn finish(mut self) -> u64 {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        self.peak()
    }
}

impl Drop for DeviceMemoryPeak {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// The GPUs sampled, their contexts opened once.
#[cfg(feature = "cuda")]
struct Gpus(Vec<std::sync::Arc<candle_core::cuda::cudarc::driver::CudaContext>>);

#[cfg(feature = "cuda")]
impl Gpus {
    /// `None` for no GPU, or when the driver does not open one of them.
    fn open(indices: &[usize]) -> Option<Self> {
        use candle_core::cuda::cudarc::driver::CudaContext;

        if indices.is_empty() {
            return None;
        }
        let contexts: Result<Vec<_>, _> = indices.iter().map(|&i| CudaContext::new(i)).collect();
        contexts.ok().map(Self)
    }

    /// The memory in use on the GPUs together (`None` when the driver does not answer).
    fn in_use(&self) -> Option<u64> {
        let mut sum = 0u64;
        for context in &self.0 {
            let (free, total) = context.mem_get_info().ok()?;
            sum += u64::try_from(total.saturating_sub(free)).unwrap_or(u64::MAX);
        }
        Some(sum)
    }
}

/// Without `cuda` there is no GPU to sample.
#[cfg(not(feature = "cuda"))]
struct Gpus;

#[cfg(not(feature = "cuda"))]
impl Gpus {
    fn open(_indices: &[usize]) -> Option<Self> {
        None
    }

    #[allow(clippy::unused_self, reason = "the signature of the build with cuda")]
    fn in_use(&self) -> Option<u64> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_is_sampled_without_a_gpu() {
        assert!(DeviceMemoryPeak::start(&[]).is_none());
        assert!(DeviceMemoryPeak::start(&[ComputeDevice::Cpu]).is_none());
        if !cfg!(feature = "cuda") {
            assert!(DeviceMemoryPeak::start(&[ComputeDevice::Cuda(0)]).is_none());
        }
    }
}
