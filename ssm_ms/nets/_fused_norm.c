/* Fused "LayerNorm over a whole feature map, then ReLU, then (optionally) the next transposed convolution" for
 * the ConvDecoder's channels-last blocks, forward and backward, float32, one row (sample) at a time.
 *
 * The next layer, when fused, is a transposed convolution whose per-pixel products are few (K^2 C2 <= C, e.g.
 * the image-drawing layer): proj [C, Q] holds its weight as (c; a, b, c2), Q = K K C2; each pixel's products are
 * added at (S i + a, S j + b) of its output [C2, (H - 1) S + K, (W - 1) S + K], with bias2 (or none).
 *
 * A row is handled in C H W order (that of nn.LayerNorm((C, H, W))'s parameters). It is read from the
 * convolution's channels-last output through pixel offsets (poff[p]: where pixel p's C contiguous channels lie in
 * that sample's memory), so the transposed convolution's phase layout is never copied into an interleaved map;
 * maps written for torch (the ReLU output, the input gradient) are channels-last [H W C] rows. With AVX-512 the
 * conversions between pixel-major and C H W order run as 16 x 16 transposes in registers. Each row is gathered
 * once into a small buffer (a sample: ~25 KB for the pendulum, in L1/L2), normalised there, and written once:
 * the feature map is read once per direction instead of the five to eight passes of separate layer-norm, ReLU
 * and convolution kernels, and with the next layer fused it is never written at all.
 *
 * Compiled on first use by ssm_ms/nets/native.py (plain C, no Python or torch headers) and called through
 * ctypes. Rows are shared among OpenMP threads: loaded into a process that has torch, the library binds to the
 * libgomp that torch loaded (same soname), so it uses torch's threads and follows torch.set_num_threads.
 * native.py only loads builds with -fopenmp (without it the pragmas would be ignored: one thread).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif
#ifdef __AVX512F__
#include <immintrin.h>

/* r[i][j] -> r[j][i] for a 16 x 16 block of floats held in 16 registers. */
static inline void transpose16(__m512 r[16])
{
    __m512 t[16], u[16];
    for (int k = 0; k < 8; ++k) {
        t[2 * k] = _mm512_unpacklo_ps(r[2 * k], r[2 * k + 1]);
        t[2 * k + 1] = _mm512_unpackhi_ps(r[2 * k], r[2 * k + 1]);
    }
    for (int G = 0; G < 4; ++G) { /* u[4 G + m], 128-bit lane L: column 4 L + m of rows 4 G .. 4 G + 3 */
        const __m512d a = _mm512_castps_pd(t[4 * G]), b = _mm512_castps_pd(t[4 * G + 1]);
        const __m512d c = _mm512_castps_pd(t[4 * G + 2]), d = _mm512_castps_pd(t[4 * G + 3]);
        u[4 * G] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        u[4 * G + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        u[4 * G + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        u[4 * G + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    for (int m = 0; m < 4; ++m) { /* the 4 x 4 transpose of 128-bit lanes */
        const __m512 v0 = _mm512_shuffle_f32x4(u[m], u[4 + m], 0x44), v1 = _mm512_shuffle_f32x4(u[m], u[4 + m], 0xEE);
        const __m512 v2 = _mm512_shuffle_f32x4(u[8 + m], u[12 + m], 0x44);
        const __m512 v3 = _mm512_shuffle_f32x4(u[8 + m], u[12 + m], 0xEE);
        r[m] = _mm512_shuffle_f32x4(v0, v2, 0x88);
        r[4 + m] = _mm512_shuffle_f32x4(v0, v2, 0xDD);
        r[8 + m] = _mm512_shuffle_f32x4(v1, v3, 0x88);
        r[12 + m] = _mm512_shuffle_f32x4(v1, v3, 0xDD);
    }
}
#endif

/* row[c P + p] = sample[poff[p] + c] (poff NULL: p C), c < C, p < P: pixel-major channels to C H W order. */
static void to_chw(const float *restrict sample, const int32_t *restrict poff, int64_t P, int64_t C,
                   float *restrict row)
{
#ifdef __AVX512F__
    for (int64_t c0 = 0; c0 < C; c0 += 16) {
        const int64_t nc = C - c0 < 16 ? C - c0 : 16;
        const __mmask16 cm = (__mmask16)((1u << nc) - 1u);
        for (int64_t p0 = 0; p0 < P; p0 += 16) {
            const int64_t np = P - p0 < 16 ? P - p0 : 16;
            __m512 r[16];
            for (int64_t i = 0; i < 16; ++i)
                r[i] = i < np ? _mm512_maskz_loadu_ps(cm, sample + (poff ? poff[p0 + i] : (p0 + i) * C) + c0)
                              : _mm512_setzero_ps();
            transpose16(r);
            const __mmask16 pm = (__mmask16)((1u << np) - 1u);
            for (int64_t c = 0; c < nc; ++c) _mm512_mask_storeu_ps(row + (c0 + c) * P + p0, pm, r[c]);
        }
    }
#else
    for (int64_t p = 0; p < P; ++p) {
        const float *restrict px = sample + (poff ? poff[p] : p * C);
        for (int64_t c = 0; c < C; ++c) row[c * P + p] = px[c];
    }
#endif
}

/* out[p C + c] = row[c P + p], c < C, p < P: C H W order to a channels-last [H W C] row. */
static void to_hwc(const float *restrict row, int64_t P, int64_t C, float *restrict out)
{
#ifdef __AVX512F__
    for (int64_t c0 = 0; c0 < C; c0 += 16) {
        const int64_t nc = C - c0 < 16 ? C - c0 : 16;
        const __mmask16 cm = (__mmask16)((1u << nc) - 1u);
        for (int64_t p0 = 0; p0 < P; p0 += 16) {
            const int64_t np = P - p0 < 16 ? P - p0 : 16;
            const __mmask16 pm = (__mmask16)((1u << np) - 1u);
            __m512 r[16];
            for (int64_t c = 0; c < 16; ++c)
                r[c] = c < nc ? _mm512_maskz_loadu_ps(pm, row + (c0 + c) * P + p0) : _mm512_setzero_ps();
            transpose16(r);
            for (int64_t i = 0; i < np; ++i) _mm512_mask_storeu_ps(out + (p0 + i) * C + c0, cm, r[i]);
        }
    }
#else
    for (int64_t p = 0; p < P; ++p)
        for (int64_t c = 0; c < C; ++c) out[p * C + c] = row[c * P + p];
#endif
}

/* How many threads the kernels use (torch's intra-op thread count when bound to torch's libgomp). */
int fused_norm_threads(void)
{
#ifdef _OPENMP
    return omp_get_max_threads();
#else
    return 1;
#endif
}

/* Row statistics of buf[0..D): mean and 1/sqrt(var + eps) (two passes over the buffer, like torch). */
static void row_stats(const float *restrict buf, int64_t D, float eps, float *mean_out, float *rstd_out)
{
    float s = 0.0f;
#pragma omp simd reduction(+ : s)
    for (int64_t k = 0; k < D; ++k) s += buf[k];
    const float mean = s / (float)D;
    float v = 0.0f;
#pragma omp simd reduction(+ : v)
    for (int64_t k = 0; k < D; ++k) {
        const float c = buf[k] - mean;
        v += c * c;
    }
    *mean_out = mean;
    *rstd_out = 1.0f / sqrtf(v / (float)D + eps);
}

/* out[m P + p] = sum_k w[k M + m] in[k P + p], m < M, p < P: the next layer's per-pixel products (and their
 * adjoint), with the sums over k kept in registers. */
static void mix(const float *restrict in, const float *restrict w, int64_t K, int64_t M, int64_t P,
                float *restrict out)
{
#ifdef __AVX512F__
    for (int64_t m0 = 0; m0 < M; m0 += 8) {
        const int64_t nm = M - m0 < 8 ? M - m0 : 8;
        for (int64_t p0 = 0; p0 < P; p0 += 16) {
            const int64_t np = P - p0 < 16 ? P - p0 : 16;
            const __mmask16 pm = (__mmask16)((1u << np) - 1u);
            __m512 acc[8];
            for (int m = 0; m < 8; ++m) acc[m] = _mm512_setzero_ps();
            for (int64_t k = 0; k < K; ++k) {
                const __m512 v = _mm512_maskz_loadu_ps(pm, in + k * P + p0);
                const float *restrict wk = w + k * M + m0;
                for (int m = 0; m < 8; ++m)
                    if (m < nm) acc[m] = _mm512_fmadd_ps(_mm512_set1_ps(wk[m]), v, acc[m]);
            }
            for (int m = 0; m < 8; ++m)
                if (m < nm) _mm512_mask_storeu_ps(out + (m0 + m) * P + p0, pm, acc[m]);
        }
    }
#else
    for (int64_t m = 0; m < M; ++m) {
        float *restrict om = out + m * P;
        for (int64_t p = 0; p < P; ++p) om[p] = 0.0f;
        for (int64_t k = 0; k < K; ++k) {
            const float wk = w[k * M + m];
            const float *restrict ik = in + k * P;
            for (int64_t p = 0; p < P; ++p) om[p] += wk * ik[p];
        }
    }
#endif
}

/* The next layer's geometry: output pixel of product q = (a, b, c2) at input pixel (i, j) of a W-wide map. */
typedef struct {
    int64_t H, W, K, S, C2, H2, W2, Q;
} next_layer;

static next_layer next_geometry(int64_t P, int64_t W, int64_t K, int64_t S, int64_t C2)
{
    next_layer g = {P / W, W, K, S, C2, (P / W - 1) * S + K, (W - 1) * S + K, K * K * C2};
    return g;
}

/* Offset in the next layer's output [C2, H2, W2] of product q's contribution from input pixel (0, 0); input row i
 * adds S i W2 (divisions: call once per product, not per row). */
static int64_t tap_offset(const next_layer *g, int64_t q)
{
    const int64_t a = q / (g->K * g->C2), b = (q / g->C2) % g->K, c2 = q % g->C2;
    return (c2 * g->H2 + a) * g->W2 + b;
}

/* h = relu(layer_norm(row) * gamma + beta), D = C P elements (P pixels per channel, W of them per map row).
 * proj == NULL: out row = h as a channels-last [H W C] row. Else out row = the next transposed convolution
 * (kernel K, stride S, C2 channels, bias2 or NULL) of h, [C2, H2, W2]. Returns 0, or -1 where scratch memory
 * could not be allocated. */
int fused_norm_forward(const float *restrict y, int64_t y_stride, const int32_t *restrict poff, int64_t D,
                       int64_t C, int64_t W,
                       const float *restrict gamma, const float *restrict beta, float eps,
                       const float *restrict proj, int64_t K, int64_t S, int64_t C2, const float *restrict bias2,
                       float *restrict out, int64_t out_stride, float *restrict mean, float *restrict rstd,
                       int64_t rows)
{
    const int64_t P = D / C;
    const next_layer g = next_geometry(P, W, K, S, C2);
    const int64_t Q = proj == NULL ? 0 : g.Q;
    int failed = 0;
#pragma omp parallel reduction(| : failed)
    {
    float *restrict buf = malloc((size_t)(D + Q * P) * sizeof(float)); /* the row, then the products [Q, P] */
    failed = buf == NULL;
    float *restrict cols = buf + D;
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows; ++r) {
        if (failed) continue;
        to_chw(y + r * y_stride, poff, P, C, buf);
        float mu, rs;
        row_stats(buf, D, eps, &mu, &rs);
        mean[r] = mu;
        rstd[r] = rs;
#pragma omp simd
        for (int64_t k = 0; k < D; ++k) {
            const float a = (buf[k] - mu) * rs * gamma[k] + beta[k];
            buf[k] = a > 0.0f ? a : 0.0f;
        }
        float *restrict o = out + r * out_stride;
        if (proj == NULL) {
            to_hwc(buf, P, C, o);
            continue;
        }
        mix(buf, proj, C, Q, P, cols);
        for (int64_t c2 = 0; c2 < C2; ++c2) {
            const float b0 = bias2 == NULL ? 0.0f : bias2[c2];
            for (int64_t k = 0; k < g.H2 * g.W2; ++k) o[c2 * g.H2 * g.W2 + k] = b0;
        }
        for (int64_t q = 0; q < Q; ++q) {
            const int64_t base = tap_offset(&g, q);
            for (int64_t i = 0; i < g.H; ++i) {
                float *restrict oi = o + base + S * i * g.W2;
                const float *restrict ci = cols + q * P + i * W;
                for (int64_t j = 0; j < W; ++j) oi[S * j] += ci[j];
            }
        }
    }
    free(buf);
    }
    return failed ? -1 : 0;
}

/* Gradients of fused_norm_forward: dx (channels-last rows of D), and the parameters' gradients summed over the
 * rows of each thread t < threads (at most fused_norm_threads()) into the caller's zeroed row t of
 * dgamma, dbeta [threads, D] (C H W order), dsum [threads, C] (the per-channel sums of dx: the preceding
 * convolution's bias gradient) and, with the next layer, dproj [threads, C Q] and dbias2 [threads, C2]; the
 * caller sums those rows in order, so that a given thread count always gives the same bits. dout rows are as the
 * forward wrote them. Returns 0, or -1 where scratch memory could not be allocated. */
int fused_norm_backward(const float *restrict y, int64_t y_stride, const int32_t *restrict poff, int64_t D,
                        int64_t C, int64_t W,
                        const float *restrict gamma, const float *restrict beta,
                        const float *restrict mean, const float *restrict rstd,
                        const float *restrict proj, int64_t K, int64_t S, int64_t C2,
                        const float *restrict dout, int64_t dout_stride, float *restrict dx,
                        float *restrict dgamma_all, float *restrict dbeta_all, float *restrict dsum_all,
                        float *restrict dproj_all, float *restrict dbias2_all, int64_t rows, int threads)
{
    const int64_t P = D / C;
    const next_layer geo = next_geometry(P, W, K, S, C2);
    const int64_t Q = proj == NULL ? 0 : geo.Q;
    float *projT = NULL; /* [Q, C]: the adjoint products' weights */
    if (Q > 0) {
        projT = malloc((size_t)(Q * C) * sizeof(float));
        if (projT == NULL) return -1;
        for (int64_t c = 0; c < C; ++c)
            for (int64_t q = 0; q < Q; ++q) projT[q * C + c] = proj[c * Q + q];
    }
    int failed = 0;
#pragma omp parallel num_threads(threads) reduction(| : failed)
    {
#ifdef _OPENMP
    const int64_t slot = omp_get_thread_num();
#else
    const int64_t slot = 0;
#endif
    float *restrict dgamma = dgamma_all + slot * D, *restrict dbeta = dbeta_all + slot * D;
    float *restrict dsum = dsum_all + slot * C;
    float *restrict dproj = proj == NULL ? NULL : dproj_all + slot * C * Q;
    float *restrict dbias2 = proj == NULL || dbias2_all == NULL ? NULL : dbias2_all + slot * C2;
    /* xhat, g [D], with the next layer t = dL/dh [D] and the products' gradients [Q, P] */
    float *restrict scratch = malloc((size_t)(2 * D + (Q > 0 ? D + Q * P : 0)) * sizeof(float));
    failed = scratch == NULL;
    float *restrict xhat = scratch, *restrict g = scratch + D, *restrict t = scratch + 2 * D;
    float *restrict dcols = t + D;
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows; ++r) {
        if (failed) continue;
        const float mu = mean[r], rs = rstd[r];
        to_chw(y + r * y_stride, poff, P, C, xhat);
#pragma omp simd
        for (int64_t k = 0; k < D; ++k) xhat[k] = (xhat[k] - mu) * rs;
        const float *restrict d = dout + r * dout_stride;
        if (proj == NULL) to_chw(d, NULL, P, C, g); /* the ReLU output's gradient, in C H W order */
        if (proj != NULL) { /* the products' gradients: the output gradient read back at each tap */
            for (int64_t q = 0; q < Q; ++q) {
                const int64_t base = tap_offset(&geo, q);
                for (int64_t i = 0; i < geo.H; ++i) {
                    const float *restrict di = d + base + S * i * geo.W2;
                    float *restrict ci = dcols + q * P + i * W;
                    for (int64_t j = 0; j < W; ++j) ci[j] = di[S * j];
                }
            }
            mix(dcols, projT, Q, C, P, t);
            if (dbias2 != NULL)
                for (int64_t c2 = 0; c2 < C2; ++c2) {
                    float acc = 0.0f;
                    const float *restrict dc = d + c2 * geo.H2 * geo.W2;
#pragma omp simd reduction(+ : acc)
                    for (int64_t k = 0; k < geo.H2 * geo.W2; ++k) acc += dc[k];
                    dbias2[c2] += acc;
                }
        }
        float s1 = 0.0f, s2 = 0.0f;
        for (int64_t c = 0; c < C; ++c) { /* channel by channel, while its slice of the row is in L1 */
            const int64_t o = c * P;
            const float *restrict xc = xhat + o, *restrict gc = gamma + o, *restrict bc = beta + o;
            float *restrict ga = g + o;
            if (proj == NULL) {
#pragma omp simd
                for (int64_t p = 0; p < P; ++p) {
                    const float a = xc[p] * gc[p] + bc[p];
                    ga[p] = a > 0.0f ? ga[p] : 0.0f; /* dL/da: the ReLU's mask */
                }
            } else {
#pragma omp simd
                for (int64_t p = 0; p < P; ++p) {
                    const float a = xc[p] * gc[p] + bc[p];
                    ga[p] = a > 0.0f ? a : 0.0f; /* h */
                }
                for (int64_t q = 0; q < Q; ++q) {
                    const float *restrict dq = dcols + q * P;
                    float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
                    for (int64_t p = 0; p < P; ++p) acc += ga[p] * dq[p];
                    dproj[c * Q + q] += acc;
                }
                const float *restrict tc = t + o; /* dL/dh of channel c */
#pragma omp simd
                for (int64_t p = 0; p < P; ++p) ga[p] = ga[p] > 0.0f ? tc[p] : 0.0f;
            }
            float *restrict dgc = dgamma + o, *restrict dbc = dbeta + o;
#pragma omp simd reduction(+ : s1, s2)
            for (int64_t p = 0; p < P; ++p) {
                const float da = ga[p];
                dbc[p] += da;
                dgc[p] += da * xc[p];
                const float gg = da * gc[p];
                ga[p] = gg;
                s1 += gg;
                s2 += gg * xc[p];
            }
        }
        const float m1 = s1 / (float)D, m2 = s2 / (float)D;
        float *restrict dxr = dx + r * D;
        for (int64_t c = 0; c < C; ++c) {
            const int64_t o = c * P;
            const float *restrict xc = xhat + o;
            float *restrict ga = g + o;
            float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
            for (int64_t p = 0; p < P; ++p) {
                const float v = rs * (ga[p] - m1 - xc[p] * m2);
                ga[p] = v;
                acc += v;
            }
            dsum[c] += acc;
        }
        to_hwc(g, P, C, dxr);
    }
    free(scratch);
    }
    free(projT);
    return failed ? -1 : 0;
}
