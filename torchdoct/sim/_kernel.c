/* Fused float32 kernels of the point simulator (torchdoct.sim.kernel holds the reference in torch).
 *
 * Every function here is the exact same sequence of IEEE-754 float32 operations as its torch twin in
 * kernel.py: no fused multiply-add (built with -ffp-contract=off), no reassociation (no -ffast-math),
 * rounding to integers by the 1.5·2^23 trick, polynomial exp/log/sin/cos with the constants below,
 * and field sums accumulated exactly in 64-bit integers (each term quantized to 2^-30), so the
 * compiled kernel and the reference give bit-identical results, in any order of summation.
 *
 * Units: positions µm, times s, phases in turns (1 turn = 2π rad).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define RINT_MAGIC 12582912.0f /* 1.5·2^23: (x + M) − M rounds |x| < 2^22 to the nearest integer, ties to even */
#define QUANT_SCALE 1073741824.0f /* 2^30 */
#define EXP_FLOOR -87.0f

/* Vector width by the CPU at run time (same IEEE operations, so the same bits on every clone). */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define CLONES __attribute__((target_clones("default", "avx2", "arch=x86-64-v4")))
#else
#define CLONES
#endif

static inline float rint_m(float x) { return (x + RINT_MAGIC) - RINT_MAGIC; }

static inline float bits_to_float(uint32_t u) { float f; memcpy(&f, &u, 4); return f; }
static inline uint32_t float_to_bits(float f) { uint32_t u; memcpy(&u, &f, 4); return u; }

/* exp(x) for x ≤ 0 (clamped at −87): x = k·ln2 + r, |r| ≤ ln2/2, Taylor polynomial of degree 7. */
static inline float exp_neg(float x) {
    x = x < EXP_FLOOR ? EXP_FLOOR : x;
    float k = rint_m(x * 0x1.715476p+0f);
    float r = (x - k * 0x1.62e4p-1f) - k * 0x1.7f7d1cp-20f;
    float p = 0x1.a01a02p-13f;
    p = p * r + 0x1.6c16c2p-10f;
    p = p * r + 0x1.111112p-7f;
    p = p * r + 0x1.555556p-5f;
    p = p * r + 0x1.555556p-3f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    return p * bits_to_float((uint32_t)((int32_t)k + 127) << 23);
}

/* sin and cos of 2π·t (t in turns, |t| < 2^20): quadrant n = rint(4t), |r| ≤ 1/8 turn, Taylor
 * polynomials of degree 9 (sin) and 10 (cos) in a = 2π·r. */
static inline void sincos_turns(float t, float *sn, float *cs) {
    float n = rint_m(t * 4.0f);
    float a = (t - n * 0.25f) * 0x1.921fb6p+2f;
    float a2 = a * a;
    float ps = 0x1.71de3ap-19f;
    ps = ps * a2 + -0x1.a01a02p-13f;
    ps = ps * a2 + 0x1.111112p-7f;
    ps = ps * a2 + -0x1.555556p-3f;
    float s = ps * a2;
    s = s * a;
    s = s + a;
    float pc = -0x1.27e4fcp-22f;
    pc = pc * a2 + 0x1.a01a02p-16f;
    pc = pc * a2 + -0x1.6c16c2p-10f;
    pc = pc * a2 + 0x1.555556p-5f;
    pc = pc * a2 + -0.5f;
    float c = pc * a2 + 1.0f;
    int32_t q = ((int32_t)n) & 3;
    float s_out = q == 0 ? s : (q == 1 ? c : (q == 2 ? -s : -c));
    float c_out = q == 0 ? c : (q == 1 ? -s : (q == 2 ? -c : s));
    *sn = s_out;
    *cs = c_out;
}

/* log(u) for 0 < u < ∞ (normal numbers): u = m·2^e with m in [1, √2)·(1 or ½), log m = 2·atanh(s),
 * s = (m − 1)/(m + 1), odd series to s^9. */
static inline float log_pos(float u) {
    uint32_t b = float_to_bits(u);
    int32_t e = (int32_t)(b >> 23) - 127;
    float m = bits_to_float((b & 0x7fffffu) | 0x3f800000u);
    int big = m > 0x1.6a09e6p+0f;
    m = big ? m * 0.5f : m;
    e = big ? e + 1 : e;
    float f = m - 1.0f;
    float s = f / (f + 2.0f);
    float s2 = s * s;
    float p = 0x1.c71c72p-4f;
    p = p * s2 + 0x1.24924ap-3f;
    p = p * s2 + 0x1.99999ap-3f;
    p = p * s2 + 0x1.555556p-2f;
    float t = p * s2;
    t = t * s;
    t = t + s;
    return (float)e * 0x1.62e43p-1f + t * 2.0f;
}

/* SplitMix64's output function (Steele, Lea & Flood 2014) at index n of the stream of `key`. */
static inline uint64_t splitmix64(uint64_t key, uint64_t n) {
    uint64_t z = key + n * 0x9e3779b97f4a7c15ull;
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

/* Two standard normals from hash h by Box–Muller: u1 = (h>>41 + ½)·2^-23 in (0, 1), u2 = (h mod 2^24)·2^-24. */
static inline void box_muller(uint64_t h, float *z0, float *z1) {
    float u1 = ((float)(uint32_t)(h >> 41) + 0.5f) * 0x1p-23f;
    float u2 = (float)(uint32_t)(h & 0xffffffu) * 0x1p-24f;
    float r = sqrtf(log_pos(u1) * -2.0f); /* correctly rounded (the reference rounds the double root: the same) */
    float sn, cs;
    sincos_turns(u2, &sn, &cs);
    *z0 = r * cs;
    *z1 = r * sn;
}

/* A field term quantized to 2^-30 (|v| ≤ 1 in use): rounded to nearest below 2^22 units, truncated above. */
static inline int32_t quantize(float v) {
    float y = v * QUANT_SCALE;
    float r = fabsf(y) < 4194304.0f ? rint_m(y) : y;
    return (int32_t)r;
}

/* ---- exported, for the bit-identity tests ---- */

CLONES void tdk_exp_neg(int64_t n, const float *x, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = exp_neg(x[i]);
}

CLONES void tdk_sincos_turns(int64_t n, const float *t, float *sn, float *cs) {
    for (int64_t i = 0; i < n; i++) sincos_turns(t[i], &sn[i], &cs[i]);
}

CLONES void tdk_log_pos(int64_t n, const float *u, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = log_pos(u[i]);
}

/* Normals z[0..n) of frame `frame`: pair p comes from splitmix64(key, frame·2^32 + p). */
CLONES void tdk_normals(uint64_t key, int64_t frame, int64_t n, float *z) {
    int64_t pairs = n / 2;
    uint64_t base = (uint64_t)frame << 32;
    for (int64_t p = 0; p < pairs; p++) box_muller(splitmix64(key, base + (uint64_t)p), &z[2 * p], &z[2 * p + 1]);
    if (n & 1) {
        float spare;
        box_muller(splitmix64(key, base + (uint64_t)pairs), &z[n - 1], &spare);
    }
}

/* Pure diffusion on the periodic cell, one block of trials (see kernel.walk_periodic).
 *   M scatterers laid out trial after trial (counts[b] each), pos [3, M] (µm, updated in place);
 *   frame f ≥ 1: pos += sigma[f−1]·z (z from tdk_normals(key, f, 3M)), then pos −= L·rint(pos/L);
 *   per PSF group g: amplitude exp(−a_lat[g]·(x²+y²) − a_ax[g]·z²), 0 below log_tol;
 *   per system s: acc[b, s, f, 0/1] += quantize(amp·cos/sin(2π·q[s]·z)).
 * Returns 0, or −1 if the scratch memory could not be allocated. */
CLONES int tdk_walk_periodic(int64_t M, int32_t n_trials, const int64_t *counts, float *pos, uint64_t key,
                      int32_t T, const float *sigma, const float *L, const float *inv_L, int32_t G,
                      const float *a_lat, const float *a_ax, int32_t S, const int32_t *group_of,
                      const float *q, float log_tol, int64_t *acc) {
    float *z = malloc(sizeof(float) * (size_t)(3 * M + 1));
    float *amp = malloc(sizeof(float) * (size_t)(M + 1));
    if (!z || !amp) { free(z); free(amp); return -1; }
    float *px = pos, *py = pos + M, *pz = pos + 2 * M;
    memset(acc, 0, sizeof(int64_t) * (size_t)n_trials * (size_t)S * (size_t)T * 2);
    for (int32_t f = 0; f < T; f++) {
        if (f > 0) {
            tdk_normals(key, f, 3 * M, z);
            float sg = sigma[f - 1];
            for (int c = 0; c < 3; c++) {
                float *p = pos + c * M, *zc = z + c * M;
                float l = L[c], il = inv_L[c];
                for (int64_t i = 0; i < M; i++) {
                    float v = p[i] + zc[i] * sg;
                    float w = rint_m(v * il);
                    p[i] = v - w * l;
                }
            }
        }
        for (int32_t g = 0; g < G; g++) {
            float al = a_lat[g], az = a_ax[g];
            for (int64_t i = 0; i < M; i++) {
                float r2 = px[i] * px[i] + py[i] * py[i];
                float ex = r2 * -al - (pz[i] * pz[i]) * az;
                amp[i] = ex >= log_tol ? exp_neg(ex) : 0.0f;
            }
            for (int32_t s = 0; s < S; s++) {
                if (group_of[s] != g) continue;
                float qs = q[s];
                int64_t i0 = 0;
                for (int32_t b = 0; b < n_trials; b++) {
                    int64_t i1 = i0 + counts[b];
                    int64_t re = 0, im = 0;
                    for (int64_t i = i0; i < i1; i++) {
                        float sn, cs;
                        sincos_turns(pz[i] * qs, &sn, &cs);
                        re += quantize(amp[i] * cs);
                        im += quantize(amp[i] * sn);
                    }
                    int64_t *o = acc + (((int64_t)b * S + s) * T + f) * 2;
                    o[0] = re;
                    o[1] = im;
                    i0 = i1;
                }
            }
        }
    }
    free(z);
    free(amp);
    return 0;
}

/* Straight paths (see kernel.eval_straight): per trial b and path c (C slots per trial), the exponent
 * e + a2·τ² and the phase φ + ω·τ (turns) at τ = t_f − t*, counted where the exponent ≥ log_tol:
 * acc[b, f, 0/1] += quantize(exp(exponent)·cos/sin(2π·phase)). Dense over the paths of a trial (one
 * vector loop per frame), which costs less than visiting each path's visible frames only. */
CLONES void tdk_eval_straight(int32_t n_trials, int64_t C, const float *e, const float *a2, const float *t_star,
                              const float *phi, const float *omega, int32_t T, const float *times, float log_tol,
                              int64_t *acc) {
    for (int32_t b = 0; b < n_trials; b++) {
        const float *eb = e + (int64_t)b * C, *ab = a2 + (int64_t)b * C, *tb = t_star + (int64_t)b * C;
        const float *pb = phi + (int64_t)b * C, *ob = omega + (int64_t)b * C;
        for (int32_t f = 0; f < T; f++) {
            float t = times[f];
            int64_t re = 0, im = 0;
            for (int64_t c = 0; c < C; c++) {
                float tau = t - tb[c];
                float ex = (tau * tau) * ab[c] + eb[c];
                float amp = (ex >= log_tol && eb[c] >= log_tol) ? exp_neg(ex) : 0.0f;
                float sn, cs;
                sincos_turns(tau * ob[c] + pb[c], &sn, &cs);
                re += quantize(amp * cs);
                im += quantize(amp * sn);
            }
            acc[((int64_t)b * T + f) * 2] = re;
            acc[((int64_t)b * T + f) * 2 + 1] = im;
        }
    }
}

/* A Python module only so that setuptools builds and installs the library; it is used through ctypes. */
static struct PyModuleDef kernel_module = {PyModuleDef_HEAD_INIT, "_kernel",
                                           "Fused float32 simulator kernels (used through ctypes).", -1, NULL};

PyMODINIT_FUNC PyInit__kernel(void) { return PyModule_Create(&kernel_module); }
