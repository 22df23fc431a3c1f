//! Compiles the fused attention kernel (`src/fused_attention.cu`) to PTX when the `cuda` feature
//! is on, with the nvcc candle's own kernels are built with (on `PATH`, or `$NVCC`; see
//! bench/gpu/cuda-toolchain.sh) for the GPU generation `CUDA_COMPUTE_CAP` names (as candle reads
//! it; 80 when unset: the PTX of an older generation runs on newer GPUs through the driver's
//! compiler; below 8.0 the kernel is left out). Without `cuda` it does nothing.

use std::env;
use std::path::PathBuf;
use std::process::Command;

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=src/fused_attention.cu");
    println!("cargo::rerun-if-env-changed=CUDA_COMPUTE_CAP");
    println!("cargo::rerun-if-env-changed=NVCC");
    if env::var_os("CARGO_FEATURE_CUDA").is_none() {
        return;
    }
    let Some(out_dir) = env::var_os("OUT_DIR").map(PathBuf::from) else {
        fail("cargo did not set OUT_DIR");
    };
    let ptx = out_dir.join("fused_attention.ptx");
    let cap = env::var("CUDA_COMPUTE_CAP").unwrap_or_else(|_| "80".to_owned());
    let cap: String = cap.chars().filter(char::is_ascii_digit).collect();
    if cap.parse::<u32>().map_or(true, |c| c < 80) {
        // Older GPUs (bf16 tensor cores came with 8.0) build without the kernel: turning the
        // fused attention on there is an error that says so (an empty module).
        println!(
            "cargo::warning=CUDA_COMPUTE_CAP {cap:?}: the fused attention kernel needs 8.0 or \
             newer and is left out"
        );
        if let Err(e) = std::fs::write(&ptx, "") {
            fail(&format!("writing {}: {e}", ptx.display()));
        }
        return;
    }
    let nvcc = env::var("NVCC").unwrap_or_else(|_| "nvcc".to_owned());
    let status = Command::new(&nvcc)
        .args(["--ptx", "-O3", "-std=c++17"])
        .arg(format!("-arch=sm_{cap}"))
        .arg("src/fused_attention.cu")
        .arg("-o")
        .arg(&ptx)
        .status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => fail(&format!("{nvcc} failed on src/fused_attention.cu ({s})")),
        Err(e) => fail(&format!(
            "could not run {nvcc} ({e}): the `cuda` feature needs nvcc on PATH or in $NVCC \
             (bench/gpu/cuda-toolchain.sh installs it from PyPI)"
        )),
    }
}

/// Stops the build with `message` (a build script reports by exiting non-zero).
fn fail(message: &str) -> ! {
    eprintln!("vlem-backends build: {message}");
    std::process::exit(1);
}
