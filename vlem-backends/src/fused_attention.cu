// Fused attention for the candle models on an NVIDIA GPU: softmax(q·kᵀ·scale)·v in one kernel,
// the scores never written to global memory (vlem_backends::fused_attention, whose plain twin in
// Rust runs the same tiles and the same online softmax on the CPU for the tests).
//
// Why it exists: candle runs attention as two cuBLAS products and a softmax, writing and reading
// the (tokens × tokens) scores of every head through global memory; at ViT-L's 1200 tokens that
// traffic, not the arithmetic, is the step's cost, and PyTorch's SDPA avoids it.
//
// Layout: q (rows, nq, D), k and v (rows, nk, D), out (rows, nq, D), contiguous, rows = batch ×
// heads; f16 or bf16 with D = 32 or 64. One block of four warps takes 64 queries of one row
// (16 per warp, held in tensor-core fragments) and walks the keys 64 at a time: K and V tiles in
// shared memory, the warp's 16 × 64 scores by tensor-core products (f32 accumulation) into
// shared memory, the running row maximum and sum updated there (each lane two columns of a row,
// warp shuffles for the row's maximum and sum), the probabilities rounded to the input type for
// the tensor-core product with V, whose 16 × D tile each lane adds to its f32 share of the output
// after scaling the running output by the change of maximum. Queries past nq compute and are
// not stored; keys past nk are masked to -inf.

#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <mma.h>

using namespace nvcuda;

namespace {

constexpr int WARPS = 4;
constexpr int ROWS = 16 * WARPS;  // queries per block
constexpr int KEYS = 64;          // keys per tile
constexpr int SLD = KEYS + 4;     // row stride of the f32 score tile (a multiple of 4)
constexpr int PLD = KEYS + 8;     // row stride of the probability tile (a multiple of 8)

template <typename T>
__device__ __forceinline__ T from_f32(float x);
template <>
__device__ __forceinline__ __half from_f32<__half>(float x) {
    return __float2half(x);
}
template <>
__device__ __forceinline__ __nv_bfloat16 from_f32<__nv_bfloat16>(float x) {
    return __float2bfloat16(x);
}

__device__ __forceinline__ float warp_max(float x) {
#pragma unroll
    for (int offset = 16; offset > 0; offset /= 2) {
        x = fmaxf(x, __shfl_xor_sync(0xffffffffu, x, offset));
    }
    return x;
}

__device__ __forceinline__ float warp_sum(float x) {
#pragma unroll
    for (int offset = 16; offset > 0; offset /= 2) {
        x += __shfl_xor_sync(0xffffffffu, x, offset);
    }
    return x;
}

// Rows first..first + 64 of a (n, D) matrix into shared memory with row stride D + 8, rows past
// n as zeros; 16-byte loads (the host checks the alignment).
template <typename T, int D>
__device__ __forceinline__ void load_tile(T* dst, const T* src, int first, int n) {
    constexpr int LD = D + 8;
    constexpr int VECTORS = D / 8;  // 16 bytes = 8 values
    for (int i = threadIdx.x; i < 64 * VECTORS; i += blockDim.x) {
        const int r = i / VECTORS;
        const int c = i % VECTORS;
        const int row = first + r;
        uint4 value = make_uint4(0, 0, 0, 0);
        if (row < n) {
            value = reinterpret_cast<const uint4*>(src + static_cast<size_t>(row) * D)[c];
        }
        *reinterpret_cast<uint4*>(dst + r * LD + c * 8) = value;
    }
}

template <typename T, int D>
__device__ __forceinline__ void attend(const T* __restrict__ q, const T* __restrict__ k,
                                       const T* __restrict__ v, T* __restrict__ out, int nq,
                                       int nk, float scale_log2) {
    constexpr int LD = D + 8;        // row stride of the Q, K and V tiles
    constexpr int TILE = KEYS * LD;  // values in one K or V tile
    constexpr int COLS = D / 32;     // output columns of a row per lane
    constexpr int SCORES = WARPS * 16 * SLD;
    static_assert(ROWS * LD * sizeof(T) <= SCORES * sizeof(float), "Q is staged in the scores");
    __shared__ __align__(128) unsigned char smem[2 * TILE * sizeof(T) + SCORES * sizeof(float) +
                                                 WARPS * 16 * PLD * sizeof(T)];
    T* ks = reinterpret_cast<T*>(smem);
    T* vs = ks + TILE;
    float* scores_all = reinterpret_cast<float*>(vs + TILE);
    T* probs_all = reinterpret_cast<T*>(scores_all + SCORES);

    const int warp = threadIdx.x / 32;
    const int lane = threadIdx.x % 32;
    float* scores = scores_all + warp * 16 * SLD;
    T* probs = probs_all + warp * 16 * PLD;
    const size_t row = blockIdx.y;
    const int q0 = blockIdx.x * ROWS;
    q += row * nq * D;
    k += row * nk * D;
    v += row * nk * D;
    out += row * nq * D;

    // The block's queries pass through the score tile (unused until the first product) into
    // each warp's fragments, where they stay.
    T* qs = reinterpret_cast<T*>(scores_all);
    load_tile<T, D>(qs, q, q0, nq);
    __syncthreads();
    wmma::fragment<wmma::matrix_a, 16, 16, 16, T, wmma::row_major> qf[D / 16];
#pragma unroll
    for (int kk = 0; kk < D / 16; ++kk) {
        wmma::load_matrix_sync(qf[kk], qs + warp * 16 * LD + kk * 16, LD);
    }
    __syncthreads();

    float m[16];
    float l[16];
    float o[16][COLS];
#pragma unroll
    for (int r = 0; r < 16; ++r) {
        m[r] = -INFINITY;
        l[r] = 0.0f;
#pragma unroll
        for (int c = 0; c < COLS; ++c) {
            o[r][c] = 0.0f;
        }
    }

    for (int k0 = 0; k0 < nk; k0 += KEYS) {
        load_tile<T, D>(ks, k, k0, nk);
        load_tile<T, D>(vs, v, k0, nk);
        __syncthreads();

        // The warp's 16 × 64 scores.
#pragma unroll
        for (int n = 0; n < KEYS / 16; ++n) {
            wmma::fragment<wmma::accumulator, 16, 16, 16, float> acc;
            wmma::fill_fragment(acc, 0.0f);
#pragma unroll
            for (int kk = 0; kk < D / 16; ++kk) {
                wmma::fragment<wmma::matrix_b, 16, 16, 16, T, wmma::col_major> kf;
                wmma::load_matrix_sync(kf, ks + n * 16 * LD + kk * 16, LD);
                wmma::mma_sync(acc, qf[kk], kf, acc);
            }
            wmma::store_matrix_sync(scores + n * 16, acc, SLD, wmma::mem_row_major);
        }
        __syncwarp();

        // Online softmax: lane j holds columns j and j + 32 of each row.
        const bool valid0 = k0 + lane < nk;
        const bool valid1 = k0 + lane + 32 < nk;
#pragma unroll
        for (int r = 0; r < 16; ++r) {
            const float s0 = valid0 ? scores[r * SLD + lane] * scale_log2 : -INFINITY;
            const float s1 = valid1 ? scores[r * SLD + lane + 32] * scale_log2 : -INFINITY;
            // Finite: column 0 of every tile is a key (k0 < nk).
            const float next = fmaxf(m[r], warp_max(fmaxf(s0, s1)));
            const float p0 = exp2f(s0 - next);
            const float p1 = exp2f(s1 - next);
            const float alpha = exp2f(m[r] - next);  // 0 on the first tile (m = -inf)
            l[r] = l[r] * alpha + warp_sum(p0 + p1);
            m[r] = next;
            probs[r * PLD + lane] = from_f32<T>(p0);
            probs[r * PLD + lane + 32] = from_f32<T>(p1);
#pragma unroll
            for (int c = 0; c < COLS; ++c) {
                o[r][c] *= alpha;
            }
        }
        __syncwarp();

        // The tile's share of the output, P · V, through the (now free) score tile.
#pragma unroll
        for (int n = 0; n < D / 16; ++n) {
            wmma::fragment<wmma::accumulator, 16, 16, 16, float> acc;
            wmma::fill_fragment(acc, 0.0f);
#pragma unroll
            for (int kk = 0; kk < KEYS / 16; ++kk) {
                wmma::fragment<wmma::matrix_a, 16, 16, 16, T, wmma::row_major> pf;
                wmma::fragment<wmma::matrix_b, 16, 16, 16, T, wmma::row_major> vf;
                wmma::load_matrix_sync(pf, probs + kk * 16, PLD);
                wmma::load_matrix_sync(vf, vs + kk * 16 * LD + n * 16, LD);
                wmma::mma_sync(acc, pf, vf, acc);
            }
            wmma::store_matrix_sync(scores + n * 16, acc, SLD, wmma::mem_row_major);
        }
        __syncwarp();
#pragma unroll
        for (int r = 0; r < 16; ++r) {
#pragma unroll
            for (int c = 0; c < COLS; ++c) {
                o[r][c] += scores[r * SLD + lane + 32 * c];
            }
        }
        // The next tile overwrites K, V and the scores.
        __syncthreads();
    }

#pragma unroll
    for (int r = 0; r < 16; ++r) {
        const int query = q0 + warp * 16 + r;
        if (query < nq) {
            const float inv = 1.0f / l[r];
#pragma unroll
            for (int c = 0; c < COLS; ++c) {
                out[static_cast<size_t>(query) * D + lane + 32 * c] = from_f32<T>(o[r][c] * inv);
            }
        }
    }
}

}  // namespace

#define FUSED_ATTENTION(NAME, T, D)                                                          \
    extern "C" __global__ void __launch_bounds__(128)                                        \
        NAME(const T* q, const T* k, const T* v, T* out, int nq, int nk, float scale_log2) { \
        attend<T, D>(q, k, v, out, nq, nk, scale_log2);                                      \
    }

FUSED_ATTENTION(fused_attention_f16_d32, __half, 32)
FUSED_ATTENTION(fused_attention_f16_d64, __half, 64)
FUSED_ATTENTION(fused_attention_bf16_d32, __nv_bfloat16, 32)
FUSED_ATTENTION(fused_attention_bf16_d64, __nv_bfloat16, 64)
