/* The ConvDecoder's stack of transposed convolutions with "LayerNorm over the whole map, ReLU" between them,
 * forward and backward, float32, run one sample (row) at a time in cache.
 *
 * Layer l is a transposed convolution (no padding) from a [Hin, Win, Cin] map to a [Hout, Wout, Cout] one,
 * Hout = (Hin - 1) S + K, its weight packed as w [Cin, Q] with Q = K K Cout in (a, b, c2) order (and its
 * transpose wt [Q, Cin]), bias [Cout] or NULL. Every layer but the last is followed by a LayerNorm over its
 * whole output (gamma, beta in the same H W C order) and a ReLU. All maps are pixel-major ([H W C] rows: a
 * pixel's channels contiguous), the layout in which a transposed convolution is one small matrix product,
 * products [Hin Win, Q] = map [Hin Win, Cin] @ w, followed by the shifted adds of its taps: output pixel
 * (S i + a, S j + b) gets the Cout contiguous products (a, b, :) of input pixel (i, j). The backward reads the
 * output gradient back at those pixels (the products' gradient), from which the input gradient is one matrix
 * product with wt and the weight gradient one with the input map.
 *
 * A sample's maps (tens to a few hundred KB for the pendulum and quadruple-pendulum decoders) stay in the core's
 * caches from the first layer to the last: only the layer norms' inputs (saved for the backward, written with
 * streaming stores) and the image go to memory, where separate convolution, layer-norm and ReLU kernels over the
 * batch would each stream the whole batch's maps through memory, forward and backward.
 *
 * Written for AVX-512 and for AVX2 with FMA (below: vec, VL lanes): the matrix products run as register-blocked
 * tiles (AVX-512: 12 to 28 accumulators of 16 lanes; AVX2: 8 or 9 of 8) and a pixel's channels as masked vectors.
 * In plain C loops the kernels were slower than the torch-only path, so other CPUs run that (build.py does not
 * build this file there, and it refuses to build without either). Compiled on first use by
 * ssm_ms/nets/native/build.py (plain C, no Python or torch headers) and called through ctypes with one
 * conv_stack_args struct (ssm_ms/nets/native/ops.py's ConvStackArgs mirrors it; conv_stack_args_size lets it check). Rows are shared among
 * OpenMP threads: loaded into a process that has torch, the library binds to the libgomp that torch loaded (same
 * soname), so it uses torch's threads and follows torch.set_num_threads. build.py only loads builds with -fopenmp.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif
#include <immintrin.h>

/* The vectors the kernels are written in: 16 lanes with AVX-512, 8 with AVX2 and FMA (16 registers instead of 32:
 * smaller product tiles). vload/vstore take a lane mask (lanes(n): the first n), masked-off lanes read as zero and
 * are not written (nor fault). */
#if defined(__AVX512F__)
#define VL 16
#define ROW_U 4 /* interleaved partial sums in a leftover-row product */
typedef __m512 vec;
typedef __mmask16 vmask;
static inline vmask lanes(int64_t left)
{
    return left >= 16 ? (vmask)0xFFFF : left > 0 ? (vmask)((1u << left) - 1u) : (vmask)0;
}
#define vzero() _mm512_setzero_ps()
#define vset1(x) _mm512_set1_ps(x)
#define vload(m, p) _mm512_maskz_loadu_ps(m, p)
#define vstore(p, m, v) _mm512_mask_storeu_ps(p, m, v)
#define vloadu(p) _mm512_loadu_ps(p)
#define vstream(p, v) _mm512_stream_ps(p, v)
#define vfma(a, b, c) _mm512_fmadd_ps(a, b, c)
#define vadd(a, b) _mm512_add_ps(a, b)
#define vsub(a, b) _mm512_sub_ps(a, b)
#define vzmask(m, v) _mm512_maskz_mov_ps(m, v)
#define vsum(v) _mm512_reduce_add_ps(v)
#elif defined(__AVX2__) && defined(__FMA__)
#define VL 8
#define ROW_U 2
typedef __m256 vec;
typedef __m256i vmask;
static inline vmask lanes(int64_t left)
{
    const int n = left >= 8 ? 8 : left > 0 ? (int)left : 0;
    return _mm256_cmpgt_epi32(_mm256_set1_epi32(n), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
}
static inline float vsum(vec v)
{
    const __m128 h = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    const __m128 q = _mm_add_ps(h, _mm_movehl_ps(h, h));
    return _mm_cvtss_f32(_mm_add_ss(q, _mm_movehdup_ps(q)));
}
#define vzero() _mm256_setzero_ps()
#define vset1(x) _mm256_set1_ps(x)
#define vload(m, p) _mm256_maskload_ps(p, m)
#define vstore(p, m, v) _mm256_maskstore_ps(p, m, v)
#define vloadu(p) _mm256_loadu_ps(p)
#define vstream(p, v) _mm256_stream_ps(p, v)
#define vfma(a, b, c) _mm256_fmadd_ps(a, b, c)
#define vadd(a, b) _mm256_add_ps(a, b)
#define vsub(a, b) _mm256_sub_ps(a, b)
#define vzmask(m, v) _mm256_and_ps(v, _mm256_castsi256_ps(m))
#else
#error "the native kernels need AVX-512, or AVX2 with FMA (build with -march=native on such a CPU)"
#endif

/* geo[l GEO + G_*]: a layer's geometry; ptrs[l PTRS + P_*]: its parameters (gamma, beta NULL for the last). */
enum { G_CIN, G_COUT, G_K, G_S, G_HIN, G_WIN, GEO };
enum { P_W, P_WT, P_BIAS, P_GAMMA, P_BETA, PTRS };
/* goff[l GOFF + O_*]: where a layer's gradients lie in a thread's row of grads (-1: none). */
enum { O_W, O_BIAS, O_GAMMA, O_BETA, GOFF };

#define MAX_LAYERS 16

typedef struct {
    int64_t cin, cout, k, s, hin, win, hout, wout, pin, pout, q, din, dout;
    float eps;
    const float *w, *wt, *bias, *gamma, *beta;
} layer_t;

static int describe(int64_t L, const int64_t *geo, const float *const *ptrs, const float *eps, layer_t *ly)
{
    if (L < 1 || L > MAX_LAYERS) return -2;
    for (int64_t l = 0; l < L; ++l) {
        const int64_t *g = geo + l * GEO;
        layer_t *y = ly + l;
        y->cin = g[G_CIN], y->cout = g[G_COUT], y->k = g[G_K], y->s = g[G_S], y->hin = g[G_HIN], y->win = g[G_WIN];
        y->hout = (y->hin - 1) * y->s + y->k, y->wout = (y->win - 1) * y->s + y->k;
        y->pin = y->hin * y->win, y->pout = y->hout * y->wout, y->q = y->k * y->k * y->cout;
        y->din = y->pin * y->cin, y->dout = y->pout * y->cout;
        y->eps = eps[l];
        const float *const *p = ptrs + l * PTRS;
        y->w = p[P_W], y->wt = p[P_WT], y->bias = p[P_BIAS], y->gamma = p[P_GAMMA], y->beta = p[P_BETA];
    }
    return 0;
}

/* ---- small matrix products: C[r ldc + m] (+)= sum_j A[r ra + j ja] B[j ldb + m], r < R, j < J, m < M ---- */

/* One tile: RP rows of C by NV VL-lane vectors of columns (mleft columns exist from B and C on), the sums over j
 * kept in RP NV registers. */
#define GEMM_TILE(RP, NV)                                                                                         \
    static void gemm_tile_##RP##_##NV(const float *restrict A, int64_t ra, int64_t ja, const float *restrict B,  \
                                      int64_t ldb, int64_t J, int64_t mleft, float *restrict C, int64_t ldc,     \
                                      int accumulate)                                                            \
    {                                                                                                             \
        vmask mk[NV];                                                                                         \
        _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) mk[v] = lanes(mleft - VL * v);                     \
        vec acc[RP][NV];                                                                                       \
        _Pragma("GCC unroll 16") for (int r = 0; r < RP; ++r)                                                    \
            _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) acc[r][v] = vzero();               \
        for (int64_t j = 0; j < J; ++j) {                                                                         \
            vec b[NV];                                                                                         \
            _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v)                                                \
                b[v] = vload(mk[v], B + j * ldb + VL * v);                                        \
            _Pragma("GCC unroll 16") for (int r = 0; r < RP; ++r) {                                              \
                const vec a = vset1(A[r * ra + j * ja]);                                              \
                _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) acc[r][v] = vfma(a, b[v], acc[r][v]); \
            }                                                                                                     \
        }                                                                                                         \
        _Pragma("GCC unroll 16") for (int r = 0; r < RP; ++r)                                                    \
            _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) {                                              \
                float *restrict c = C + r * ldc + VL * v;                                                         \
                const vec x = accumulate ? vadd(vload(mk[v], c), acc[r][v]) : acc[r][v]; \
                vstore(c, mk[v], x);                                                               \
            }                                                                                                     \
    }

#if VL == 16 /* 32 registers: 12 to 28 accumulators */
GEMM_TILE(12, 1)
GEMM_TILE(6, 2)
GEMM_TILE(6, 3)
GEMM_TILE(6, 4)
GEMM_TILE(4, 5)
GEMM_TILE(4, 6)
GEMM_TILE(3, 7)
#else /* 16 registers: 8 or 9 accumulators */
GEMM_TILE(8, 1)
GEMM_TILE(4, 2)
GEMM_TILE(3, 3)
GEMM_TILE(2, 4)
#endif

/* One row of C (a tile's leftover rows): the sum over j split into ROW_U interleaved partial sums, so that the
 * additions do not wait on each other (a single chain of fused multiply-adds runs at their latency, not rate). */
#define GEMM_ROW(NV)                                                                                              \
    static void gemm_tile_1_##NV(const float *restrict A, int64_t ra, int64_t ja, const float *restrict B,       \
                                 int64_t ldb, int64_t J, int64_t mleft, float *restrict C, int64_t ldc,          \
                                 int accumulate)                                                                 \
    {                                                                                                             \
        (void)ra, (void)ldc;                                                                                      \
        vmask mk[NV];                                                                                         \
        _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) mk[v] = lanes(mleft - VL * v);                     \
        vec acc[ROW_U][NV];                                                                                       \
        _Pragma("GCC unroll 16") for (int u = 0; u < ROW_U; ++u)                                                 \
            _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) acc[u][v] = vzero();                           \
        int64_t j = 0;                                                                                            \
        for (; j + ROW_U <= J; j += ROW_U)                                                                        \
            _Pragma("GCC unroll 4") for (int u = 0; u < ROW_U; ++u) {                                            \
                const vec a = vset1(A[(j + u) * ja]);                                                             \
                _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v)                                            \
                    acc[u][v] = vfma(a, vload(mk[v], B + (j + u) * ldb + VL * v), acc[u][v]);                     \
            }                                                                                                     \
        for (; j < J; ++j) {                                                                                      \
            const vec a = vset1(A[j * ja]);                                                                       \
            _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v)                                                \
                acc[0][v] = vfma(a, vload(mk[v], B + j * ldb + VL * v), acc[0][v]);                               \
        }                                                                                                         \
        _Pragma("GCC unroll 16") for (int v = 0; v < NV; ++v) {                                                  \
            vec x = acc[0][v];                                                                                    \
            _Pragma("GCC unroll 4") for (int u = 1; u < ROW_U; ++u) x = vadd(x, acc[u][v]);                      \
            if (accumulate) x = vadd(vload(mk[v], C + VL * v), x);                                                \
            vstore(C + VL * v, mk[v], x);                                                                         \
        }                                                                                                         \
    }

GEMM_ROW(1)
GEMM_ROW(2)
GEMM_ROW(3)
GEMM_ROW(4)
#if VL == 16
GEMM_ROW(5)
GEMM_ROW(6)
GEMM_ROW(7)
#endif

/* Rows in tiles of RP (the rest one by one), columns in blocks of NV vectors. */
#define GEMM_RUN(RP, NV)                                                                                          \
    for (int64_t m0 = 0; m0 < M; m0 += VL * NV) {                                                                 \
        int64_t r0 = 0;                                                                                           \
        for (; r0 + RP <= R; r0 += RP)                                                                            \
            gemm_tile_##RP##_##NV(A + r0 * ra, ra, ja, B + m0, ldb, J, M - m0, C + r0 * ldc + m0, ldc, accumulate); \
        for (; r0 < R; ++r0)                                                                                      \
            gemm_tile_1_##NV(A + r0 * ra, ra, ja, B + m0, ldb, J, M - m0, C + r0 * ldc + m0, ldc, accumulate);    \
    }

static void gemm(const float *restrict A, int64_t ra, int64_t ja, const float *restrict B, int64_t ldb, int64_t R,
                 int64_t J, int64_t M, float *restrict C, int64_t ldc, int accumulate)
{
#if VL == 16
    switch ((M + 15) / 16) { /* the tile shape by the number of column vectors */
    case 1: GEMM_RUN(12, 1) break;
    case 2: GEMM_RUN(6, 2) break;
    case 3: GEMM_RUN(6, 3) break;
    case 4: GEMM_RUN(6, 4) break;
    case 5: GEMM_RUN(4, 5) break;
    case 6: GEMM_RUN(4, 6) break;
    case 7: GEMM_RUN(3, 7) break;
    default: GEMM_RUN(4, 5) break;
    }
#else
    switch ((M + 7) / 8) {
    case 1: GEMM_RUN(8, 1) break;
    case 2: GEMM_RUN(4, 2) break;
    case 3: GEMM_RUN(3, 3) break;
    default: GEMM_RUN(2, 4) break;
    }
#endif
}

/* dst[0..n) += src[0..n), or = with copy: one pixel's channels */
static inline void pixel_op(float *restrict dst, const float *restrict src, int64_t n, int copy)
{
    for (int64_t c = 0; c < n; c += VL) {
        const vmask m = lanes(n - c);
        const vec v = vload(m, src + c);
        vstore(dst + c, m, copy ? v : vadd(vload(m, dst + c), v));
    }
}

/* dst[j dstep + c] (+)= src[j sstep + c], j < W, c < C: one strip of pixels, a pixel's C channels at a time
 * (sstep 0: the same C values into every pixel). */
static inline void strip(float *restrict dst, int64_t dstep, const float *restrict src, int64_t sstep, int64_t W,
                         int64_t C, int copy)
{
    if (C == 1) {
        for (int64_t j = 0; j < W; ++j) dst[j * dstep] = copy ? src[j * sstep] : dst[j * dstep] + src[j * sstep];
        return;
    }
    if (C <= VL) { /* one masked vector per pixel */
        const vmask m = lanes(C);
        for (int64_t j = 0; j < W; ++j) {
            const vec v = vload(m, src + j * sstep);
            float *restrict d = dst + j * dstep;
            vstore(d, m, copy ? v : vadd(vload(m, d), v));
        }
        return;
    }
    for (int64_t j = 0; j < W; ++j) pixel_op(dst + j * dstep, src + j * sstep, C, copy);
}

/* Output pixel (S i + a, S j + b) and product (a, b, :) of input pixel (i, j), for every i, j, a, b: the
 * transposed convolution's shifted adds (forward: out += prod) or their adjoint (backward: prod = out, the output
 * gradient read back at each product), as strips over j: for fixed (i, a, b) the pixels j are distinct, so
 * consecutive adds never wait on each other's stores. */
static void taps_forward(const layer_t *ly, const float *restrict prod, float *restrict out)
{
    const int64_t C = ly->cout, Q = ly->q, S = ly->s, W = ly->win;
    for (int64_t i = 0; i < ly->hin; ++i)
        for (int64_t a = 0; a < ly->k; ++a)
            for (int64_t b = 0; b < ly->k; ++b)
                strip(out + ((S * i + a) * ly->wout + b) * C, S * C, prod + i * W * Q + (a * ly->k + b) * C, Q, W, C,
                      0);
}

static void taps_backward(const layer_t *ly, const float *restrict dout, float *restrict dprod)
{
    const int64_t C = ly->cout, Q = ly->q, S = ly->s, W = ly->win;
    for (int64_t i = 0; i < ly->hin; ++i)
        for (int64_t a = 0; a < ly->k; ++a)
            for (int64_t b = 0; b < ly->k; ++b)
                strip(dprod + i * W * Q + (a * ly->k + b) * C, Q, dout + ((S * i + a) * ly->wout + b) * C, S * C, W, C,
                      1);
}

/* acc[c] += sum_p d[p C + c], c < C (a bias gradient), with independent partial sums. */
static void channel_sums(const float *restrict d, int64_t P, int64_t C, float *restrict acc)
{
    if (C == 1) {
        float s = 0.0f;
#pragma omp simd reduction(+ : s)
        for (int64_t p = 0; p < P; ++p) s += d[p];
        acc[0] += s;
        return;
    }
    for (int64_t c = 0; c < C; c += VL) {
        const vmask m = lanes(C - c);
        vec s0 = vzero(), s1 = s0, s2 = s0, s3 = s0;
        int64_t p = 0;
        for (; p + 4 <= P; p += 4) {
            s0 = vadd(s0, vload(m, d + p * C + c));
            s1 = vadd(s1, vload(m, d + (p + 1) * C + c));
            s2 = vadd(s2, vload(m, d + (p + 2) * C + c));
            s3 = vadd(s3, vload(m, d + (p + 3) * C + c));
        }
        for (; p < P; ++p) s0 = vadd(s0, vload(m, d + p * C + c));
        const vec t = vadd(vadd(s0, s1), vadd(s2, s3));
        vstore(acc + c, m, vadd(vload(m, acc + c), t));
    }
}

/* ---- one layer ---- */

/* out [Pout, Cout] = the layer applied to in [Pin, Cin], through the products prod [Pin, Q]. */
static void layer_forward(const layer_t *ly, const float *restrict in, float *restrict prod, float *restrict out)
{
    gemm(in, ly->cin, 1, ly->w, ly->q, ly->pin, ly->cin, ly->q, prod, ly->q, 0);
    if (ly->bias == NULL)
        memset(out, 0, (size_t)ly->dout * sizeof(float));
    else
        strip(out, ly->cout, ly->bias, 0, ly->pout, ly->cout, 1);
    taps_forward(ly, prod, out);
}

/* dst[0..n) = src[0..n) for a dst that is not read again soon (the saved layer-norm inputs): to a 64-byte aligned
 * dst, streaming stores, which skip reading the destination's cache lines from memory first. */
static void store_away(float *restrict dst, const float *restrict src, int64_t n)
{
    if (((uintptr_t)dst & 63) == 0) {
        int64_t k = 0;
        for (; k + VL <= n; k += VL) vstream(dst + k, vloadu(src + k));
        for (; k < n; ++k) dst[k] = src[k];
        return;
    }
    memcpy(dst, src, (size_t)n * sizeof(float));
}

/* Mean and 1/sqrt(var + eps) of y[0..D) (two passes, like torch). */
static void row_stats(const float *restrict y, int64_t D, float eps, float *mean_out, float *rstd_out)
{
    /* four independent partial sums: one chain of vector additions would run at their latency, not their rate */
    vec a[4] = {vzero(), vzero(), vzero(), vzero()};
    int64_t k = 0;
    for (; k + 4 * VL <= D; k += 4 * VL)
        for (int u = 0; u < 4; ++u) a[u] = vadd(a[u], vloadu(y + k + VL * u));
    for (; k < D; k += VL) a[0] = vadd(a[0], vload(lanes(D - k), y + k));
    const float s = vsum(vadd(vadd(a[0], a[1]), vadd(a[2], a[3])));
    const float mean = s / (float)D;
    const vec m = vset1(mean);
    for (int u = 0; u < 4; ++u) a[u] = vzero();
    for (k = 0; k + 4 * VL <= D; k += 4 * VL)
        for (int u = 0; u < 4; ++u) {
            const vec c = vsub(vloadu(y + k + VL * u), m);
            a[u] = vfma(c, c, a[u]);
        }
    for (; k < D; k += VL) {
        const vmask mk = lanes(D - k);
        const vec c = vzmask(mk, vsub(vload(mk, y + k), m));
        a[0] = vfma(c, c, a[0]);
    }
    const float v = vsum(vadd(vadd(a[0], a[1]), vadd(a[2], a[3])));
    *mean_out = mean;
    *rstd_out = 1.0f / sqrtf(v / (float)D + eps);
}

/* h = relu((y - mu) rs gamma + beta) */
static void norm_relu(const float *restrict y, int64_t D, const float *restrict gamma, const float *restrict beta,
                      float mu, float rs, float *restrict h)
{
#pragma omp simd
    for (int64_t k = 0; k < D; ++k) {
        const float a = (y[k] - mu) * rs * gamma[k] + beta[k];
        h[k] = a > 0.0f ? a : 0.0f;
    }
}

/* g: in dL/dh, out dL/dy, for h = relu(layer_norm(y) gamma + beta); dgamma, dbeta accumulate. */
static void norm_relu_backward(const float *restrict y, int64_t D, const float *restrict gamma,
                               const float *restrict beta, float mu, float rs, float *restrict g,
                               float *restrict dgamma, float *restrict dbeta)
{
    float s1 = 0.0f, s2 = 0.0f;
#pragma omp simd reduction(+ : s1, s2)
    for (int64_t k = 0; k < D; ++k) {
        const float xh = (y[k] - mu) * rs;
        const float da = xh * gamma[k] + beta[k] > 0.0f ? g[k] : 0.0f;
        dbeta[k] += da;
        dgamma[k] += da * xh;
        const float gg = da * gamma[k];
        g[k] = gg;
        s1 += gg;
        s2 += gg * xh;
    }
    const float m1 = s1 / (float)D, m2 = s2 / (float)D;
#pragma omp simd
    for (int64_t k = 0; k < D; ++k) g[k] = rs * (g[k] - m1 - (y[k] - mu) * rs * m2);
}

/* ---- the stack ---- */

/* How many threads the kernels use (torch's intra-op thread count when bound to torch's libgomp). */
int conv_stack_threads(void)
{
#ifdef _OPENMP
    return omp_get_max_threads();
#else
    return 1;
#endif
}

/* Largest products [Pin, Q] and largest layer-normed map of the stack (scratch sizes, floats). */
static void scratch_sizes(int64_t L, const layer_t *ly, int64_t *prod, int64_t *map)
{
    *prod = 0, *map = 1;
    for (int64_t l = 0; l < L; ++l) {
        if (ly[l].pin * ly[l].q > *prod) *prod = ly[l].pin * ly[l].q;
        if (l < L - 1 && ly[l].dout > *map) *map = ly[l].dout;
    }
}

/* Floats per row of conv_stack_forward's saved: each layer-normed output rounded up to 16 floats (64 bytes). */
static int64_t saved_offsets(int64_t L, const layer_t *ly, int64_t *soff)
{
    int64_t S = 0;
    for (int64_t l = 0; l < L - 1; ++l) soff[l] = S, S += (ly[l].dout + 15) / 16 * 16;
    return S;
}

/* A stack as one call sees it: its layers, scratch sizes (floats) and where each layer-normed output lies in a row of
 * the forward's saved. */
typedef struct {
    layer_t ly[MAX_LAYERS];
    int64_t nprod, nmap, S, soff[MAX_LAYERS];
} stack_geo;

static int setup(int64_t L, const int64_t *geo, const float *const *ptrs, const float *eps, stack_geo *st)
{
    if (describe(L, geo, ptrs, eps, st->ly) != 0) return -2;
    scratch_sizes(L, st->ly, &st->nprod, &st->nmap);
    st->S = saved_offsets(L, st->ly, st->soff);
    return 0;
}

/* Floats of one thread's scratch, in either direction: a products buffer and three maps. */
static int64_t scratch_floats(const stack_geo *st)
{
    return st->nprod + 3 * st->nmap;
}

/* One thread's scratch, returned for free(): buf[0] for products (nprod floats), buf[1..3] for maps (nmap each);
 * NULL where memory could not be allocated. */
static float *thread_scratch(const stack_geo *st, float *buf[4])
{
    float *scratch = malloc((size_t)scratch_floats(st) * sizeof(float));
    buf[0] = scratch;
    for (int i = 1; i < 4; ++i) buf[i] = scratch == NULL ? NULL : scratch + st->nprod + (i - 1) * st->nmap;
    return scratch;
}

/* What a call of conv_stack_forward or conv_stack_backward reads and writes, by name (ssm_ms/nets/native/ops.py's
 * ConvStackArgs is the same struct in ctypes; conv_stack_args_size lets it check that the two agree). */
typedef struct {
    int64_t layers;              /* L */
    const int64_t *geo;          /* [L GEO]: Cin, Cout, K, S, Hin, Win per layer */
    const float *const *params;  /* [L PTRS]: w, wt, bias, gamma, beta per layer (gamma, beta NULL for the last) */
    const float *eps;            /* [L]: the layer norms' epsilons */
    int64_t rows;                /* samples */
    const float *x;              /* [rows, Din of layer 0] */
    float *out;                  /* forward: [rows, Dout of the last layer] */
    float *saved;                /* [rows, conv_stack_size(L, geo, 0)]: written by the forward, read by the backward */
    float *stats;                /* [rows, 2 (L - 1)]: the same */
    const float *dout;           /* backward: [rows, Dout of the last layer] */
    float *dx;                   /* backward: [rows, Din of layer 0] */
    float *grads;                /* backward: [threads, gsize], zeroed by the caller */
    const int64_t *goff;         /* backward: [L GOFF] */
    int64_t gsize;
    int64_t threads;             /* backward: rows of grads (at most conv_stack_threads()) */
} conv_stack_args;

int64_t conv_stack_args_size(void) { return (int64_t)sizeof(conv_stack_args); }

/* Floats per row of conv_stack_forward's saved (what = 0), or of one thread's scratch in either direction (what = 1),
 * for a stack's geometry; -2 for a bad layer count. */
int64_t conv_stack_size(int64_t L, const int64_t *geo, int what)
{
    stack_geo st;
    const float *ptrs[MAX_LAYERS * PTRS] = {0};
    float eps[MAX_LAYERS] = {0};
    if (setup(L, geo, ptrs, eps, &st) != 0) return -2;
    return what == 0 ? st.S : scratch_floats(&st);
}

/* x [rows, Din of layer 0] -> out [rows, Dout of the last layer]. Saves each layer-normed layer's output y
 * (saved [rows, conv_stack_size(L, geo, 0)], in layer order, each at a multiple of 16 floats) and its mean and 1/std
 * (stats [rows, 2 (L - 1)]).
 * Returns 0, -1 where scratch memory could not be allocated, -2 for a bad layer count. */
int conv_stack_forward(const conv_stack_args *a)
{
    const int64_t L = a->layers, rows = a->rows;
    const float *restrict x = a->x;
    float *restrict out = a->out, *restrict saved = a->saved, *restrict stats = a->stats;
    stack_geo st;
    if (setup(L, a->geo, a->params, a->eps, &st) != 0) return -2;
    const layer_t *ly = st.ly;
    const int64_t S = st.S, *soff = st.soff;
    int failed = 0;
#pragma omp parallel reduction(| : failed)
    {
    float *buf[4];
    float *scratch = thread_scratch(&st, buf);
    failed = scratch == NULL;
    /* prod: the products; y: a layer's output, made in cache, then stored away; maps: the normalised maps */
    float *restrict prod = buf[0], *restrict y = buf[1], *restrict maps[2] = {buf[2], buf[3]};
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows; ++r) {
        if (failed) continue;
        const float *in = x + r * ly[0].din;
        float *restrict st = stats + r * 2 * (L - 1);
        for (int64_t l = 0; l < L - 1; ++l) {
            layer_forward(ly + l, in, prod, y);
            store_away(saved + r * S + soff[l], y, ly[l].dout);
            /* the map's padding to 16 floats: zeros, so that every float of saved is defined (a custom operator's
             * outputs are compared as a whole, e.g. by torch.library.opcheck) */
            for (int64_t k = ly[l].dout; k < (ly[l].dout + 15) / 16 * 16; ++k) saved[r * S + soff[l] + k] = 0.f;
            row_stats(y, ly[l].dout, ly[l].eps, st, st + 1);
            norm_relu(y, ly[l].dout, ly[l].gamma, ly[l].beta, st[0], st[1], maps[l & 1]);
            in = maps[l & 1];
            st += 2;
        }
        layer_forward(ly + L - 1, in, prod, out + r * ly[L - 1].dout);
    }
    free(scratch);
    }
    _mm_sfence(); /* the streaming stores are visible before the caller reads saved */
    return failed ? -1 : 0;
}

/* Gradients of conv_stack_forward given dout [rows, Dout of the last layer]: dx [rows, Din of layer 0], and the
 * parameters' gradients summed over the rows of each thread t < threads (at most conv_stack_threads()) into the
 * caller's zeroed row t of grads [threads, gsize], at goff (weights as wt's gradient [Q, Cin], gamma and beta in
 * H W C order); the caller sums those rows in order, so that a given thread count always gives the same bits.
 * Returns 0, -1 where scratch memory could not be allocated, -2 for a bad layer count. */
int conv_stack_backward(const conv_stack_args *a)
{
    const int64_t L = a->layers, rows = a->rows, gsize = a->gsize, *goff = a->goff;
    const int threads = (int)a->threads;
    const float *restrict x = a->x, *restrict saved = a->saved, *restrict stats = a->stats, *restrict dout = a->dout;
    float *restrict dx = a->dx, *restrict grads = a->grads;
    stack_geo st;
    if (setup(L, a->geo, a->params, a->eps, &st) != 0) return -2;
    const layer_t *ly = st.ly;
    const int64_t S = st.S, *soff = st.soff;
    int failed = 0;
#pragma omp parallel num_threads(threads) reduction(| : failed)
    {
#ifdef _OPENMP
    const int64_t slot = omp_get_thread_num();
#else
    const int64_t slot = 0;
#endif
    float *restrict G = grads + slot * gsize;
    float *buf[4];
    float *scratch = thread_scratch(&st, buf);
    failed = scratch == NULL;
    /* dcols: the products' gradient; h: a layer's input map; dh[2]: map gradients, alternating by layer */
    float *restrict dcols = buf[0], *restrict h = buf[1], *restrict dh[2] = {buf[2], buf[3]};
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows; ++r) {
        if (failed) continue;
        const float *d = dout + r * ly[L - 1].dout; /* the gradient of layer l's output */
        for (int64_t l = L - 1; l >= 0; --l) {
            const layer_t *c = ly + l;
            const int64_t *o = goff + l * GOFF;
            if (o[O_BIAS] >= 0) channel_sums(d, c->pout, c->cout, G + o[O_BIAS]);
            taps_backward(c, d, dcols);
            const float *in = x + r * ly[0].din, *y = NULL, *st = NULL;
            if (l > 0) { /* this layer's input: the previous layer's output, normalised again from its saved y */
                y = saved + r * S + soff[l - 1], st = stats + r * 2 * (L - 1) + 2 * (l - 1);
                norm_relu(y, ly[l - 1].dout, ly[l - 1].gamma, ly[l - 1].beta, st[0], st[1], h);
                in = h;
            }
            gemm(dcols, 1, c->q, in, c->cin, c->q, c->pin, c->cin, G + o[O_W], c->cin, 1); /* wt's: += dcols^T in */
            float *restrict g = l == 0 ? dx + r * ly[0].din : dh[l & 1];
            gemm(dcols, c->q, 1, c->wt, c->cin, c->pin, c->q, c->cin, g, c->cin, 0); /* dcols wt: dL/d(in) */
            if (l == 0) break;
            const int64_t *op = goff + (l - 1) * GOFF;
            norm_relu_backward(y, ly[l - 1].dout, ly[l - 1].gamma, ly[l - 1].beta, st[0], st[1], g,
                               G + op[O_GAMMA], G + op[O_BETA]);
            d = g;
        }
    }
    free(scratch);
    }
    return failed ? -1 : 0;
}
