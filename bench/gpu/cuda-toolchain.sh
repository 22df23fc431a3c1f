#!/usr/bin/env bash
# The CUDA 13.0 compiler, headers and libraries that vlem's `cuda` feature builds against, from
# PyPI, on a machine without a GPU or a CUDA installation (candle's build script compiles its
# kernels with nvcc; linking needs the CUDA libraries and the driver's libcuda.so).
#
#   source bench/gpu/cuda-toolchain.sh            # compiler only: enough for `cargo check`
#   source bench/gpu/cuda-toolchain.sh --link     # + cuBLAS, cuRAND, NVRTC: `cargo build`
#   cargo build --release --features ci,cuda
#
# It installs into bench/.venv-cuda (git-ignored) and exports PATH, CUDA_ROOT and
# CUDA_COMPUTE_CAP. Versions are 13.0.x to match a CUDA 13.0 driver (the `-cu12` nvcc wheels ship
# no nvcc binary). CUDA_COMPUTE_CAP defaults to 90 (H100/H200); set it first for other GPUs (89
# for an RTX 4090/4070, 86 for an RTX 3090, 87 for a Jetson Orin). With --link, lib/ gets the
# unversioned names the linker looks for and a stub libcuda.so generated from the driver symbols
# the objects use: the real driver (libcuda.so.1) replaces it at run time, so a binary built this
# way starts only where an NVIDIA driver is installed.
# Safe to source again: it installs only what is missing.

_vlem_cuda_main() {
    local link=0
    [ "${1:-}" = "--link" ] && link=1
    local repo
    repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
    local venv="$repo/bench/.venv-cuda"
    local python=${PYTHON:-python3}
    local compiler=(nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-cuda-runtime==13.0.96
        nvidia-nvvm==13.0.88 nvidia-cuda-cccl==13.0.85)
    local libraries=(nvidia-cuda-nvrtc==13.0.88 nvidia-cublas==13.0.2.14 nvidia-curand==10.4.0.35)
    [ -x "$venv/bin/python" ] || "$python" -m venv "$venv" || return 1
    local wanted=("${compiler[@]}")
    [ $link = 1 ] && wanted+=("${libraries[@]}")
    # Installed at the wanted versions? (pip show succeeds when any one of them is there.)
    if ! "$venv/bin/python" - "${wanted[@]}" <<'PY' 2>/dev/null; then
import importlib.metadata as m, sys
sys.exit(any(m.version(n) != v for n, v in (a.split("==") for a in sys.argv[1:])))
PY
        echo "cuda-toolchain: installing ${wanted[*]} into $venv" >&2
        "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "${wanted[@]}" || return 1
    fi
    local root
    root=$("$venv/bin/python" -c 'import nvidia, os; print(os.path.join(list(nvidia.__path__)[0], "cu13"))') || return 1
    chmod +x "$root/bin/"* 2>/dev/null
    export PATH="$root/bin:$PATH"
    export CUDA_ROOT="$root"
    export CUDA_PATH="$root"
    export CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}"
    if [ $link = 1 ]; then
        local lib="$root/lib" so
        for so in libcublas libcublasLt libcurand libnvrtc libcudart; do
            local versioned
            versioned=$(ls "$lib/$so.so."* 2>/dev/null | head -n 1 || true)
            [ -n "$versioned" ] && ln -sf "$(basename "$versioned")" "$lib/$so.so"
        done
        if [ ! -e "$lib/libcuda.so" ]; then
            _vlem_cuda_driver_stub "$lib" "$repo" || return 1
        fi
        export LIBRARY_PATH="$lib${LIBRARY_PATH:+:$LIBRARY_PATH}"
        export RUSTFLAGS="${RUSTFLAGS:+$RUSTFLAGS }-L native=$lib"
    fi
    echo "cuda-toolchain: nvcc $(nvcc --version | sed -n 's/.*release \([0-9.]*\).*/\1/p'), CUDA_COMPUTE_CAP=$CUDA_COMPUTE_CAP, CUDA_ROOT=$CUDA_ROOT" >&2
}

# A link-time stand-in for the driver library: every `cu*` function the CUDA crates may call, as an
# empty symbol in libcuda.so with the soname of the real one. Nothing ever runs it: the dynamic
# loader binds the binary to the machine's own libcuda.so.1.
_vlem_cuda_driver_stub() {
    local lib=$1 repo=$2 registry symbols
    _vlem_cudarc_sources() {
        ls -d "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/cudarc-0.19.* 2>/dev/null | tail -n 1
    }
    registry=$(_vlem_cudarc_sources)
    if [ -z "$registry" ]; then
        # A fresh clone on a fresh machine: the sources come with the workspace's locked crates.
        echo "cuda-toolchain: fetching the workspace's crates for cudarc's driver functions" >&2
        (cd "$repo" && cargo fetch --locked --quiet) || return 1
        registry=$(_vlem_cudarc_sources)
    fi
    if [ -z "$registry" ]; then
        echo "cuda-toolchain: no cudarc 0.19 sources under ${CARGO_HOME:-$HOME/.cargo}/registry/src after 'cargo fetch'" >&2
        return 1
    fi
    symbols=$(grep -rhoE 'pub (unsafe )?fn cu[A-Za-z0-9_]+' "$registry/src/driver/sys" |
        sed -E 's/pub (unsafe )?fn //' | sort -u)
    if [ -z "$symbols" ]; then
        echo "cuda-toolchain: no driver functions found in $registry" >&2
        return 1
    fi
    local c="$lib/libcuda_stub.c"
    : >"$c"
    local s
    for s in $symbols; do echo "void $s(void) {}" >>"$c"; done
    gcc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$lib/libcuda.so" "$c" || return 1
}

_vlem_cuda_main "$@"
