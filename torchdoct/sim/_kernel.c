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
#ifndef TORCHDOCT_NO_PYTHON
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#endif
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
    float r = sqrtf(log_pos(u1) * -2.0f);
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

/* The taper window of the exponent ex (≤ 0) of a scatterer above the tolerance (see
 * torchdoct.conventions.taper_window): 1 for ex ≥ e0 = a·ln tol, else 1 − t³(10 − 15t + 6t²) with
 * t = min((ex − e0)·tk, 1), tk = 1/((1 − a)·ln tol), which reaches 0 at ex = ln tol (C²). */
static inline float taper_w(float ex, float e0, float tk) {
    float t = (ex - e0) * tk;
    t = t < 1.0f ? t : 1.0f;
    float t3 = (t * t) * t;
    float p = t * 6.0f;
    p = p - 15.0f;
    p = p * t;
    p = p + 10.0f;
    float w = 1.0f - t3 * p;
    return ex >= e0 ? 1.0f : w;
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

CLONES void tdk_taper(int64_t n, const float *ex, float e0, float tk, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = taper_w(ex[i], e0, tk);
}

/* Counter of the normal pair p of component `comp` at frame `frame`: frame·2^32 + comp·2^30 + p. */
static inline uint64_t pair_index(int64_t frame, int32_t comp, int64_t p) {
    return ((uint64_t)frame << 32) | ((uint64_t)comp << 30) | (uint64_t)p;
}

/* Normals of pairs q0 ≤ q < q1 (component comp, frame): z[2(q−q0)] and z[2(q−q0)+1], by Box–Muller. */
static inline void normal_pairs(uint64_t key, int64_t frame, int32_t comp, int64_t q0, int64_t q1, float *z) {
    for (int64_t q = q0; q < q1; q++)
        box_muller(splitmix64(key, pair_index(frame, comp, q)), &z[2 * (q - q0)], &z[2 * (q - q0) + 1]);
}

/* Normals z[0..n) of scatterers 0..n−1 for (frame, comp): scatterer i takes the first (even i) or
 * second (odd i) normal of pair i/2. */
CLONES void tdk_normals(uint64_t key, int64_t frame, int32_t comp, int64_t n, float *z) {
    int64_t pairs = n / 2;
    normal_pairs(key, frame, comp, 0, pairs, z);
    if (n & 1) {
        float two[2];
        normal_pairs(key, frame, comp, pairs, pairs + 1, two);
        z[n - 1] = two[0];
    }
}


/* Compaction of the scatterers above the tolerance: (ex[i], z[i]) for ex[i] >= log_tol, in order.
 * Exact (a copy); with AVX-512 by compress-stores, else a scalar loop. */
static int64_t compact_scalar(int64_t n, const float *ex, const float *z, float log_tol, float *kex, float *kz) {
    int64_t k = 0;
    for (int64_t i = 0; i < n; i++) {
        kex[k] = ex[i];
        kz[k] = z[i];
        k += ex[i] >= log_tol;
    }
    return k;
}
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
__attribute__((target("avx512f"))) static int64_t compact_avx512(int64_t n, const float *ex, const float *z,
                                                                  float log_tol, float *kex, float *kz) {
    int64_t k = 0, i = 0;
    __m512 tol = _mm512_set1_ps(log_tol);
    for (; i + 16 <= n; i += 16) {
        __m512 e = _mm512_loadu_ps(ex + i);
        __mmask16 m = _mm512_cmp_ps_mask(e, tol, _CMP_GE_OQ);
        _mm512_mask_compressstoreu_ps(kex + k, m, e);
        _mm512_mask_compressstoreu_ps(kz + k, m, _mm512_loadu_ps(z + i));
        k += __builtin_popcount((unsigned)m);
    }
    return k + compact_scalar(n - i, ex + i, z + i, log_tol, kex + k, kz + k);
}
static int64_t (*compact_fn)(int64_t, const float *, const float *, float, float *, float *) = 0;
static int64_t compact(int64_t n, const float *ex, const float *z, float log_tol, float *kex, float *kz) {
    if (!compact_fn) compact_fn = __builtin_cpu_supports("avx512f") ? compact_avx512 : compact_scalar;
    return compact_fn(n, ex, z, log_tol, kex, kz);
}
#else
static int64_t compact(int64_t n, const float *ex, const float *z, float log_tol, float *kex, float *kz) {
    return compact_scalar(n, ex, z, log_tol, kex, kz);
}
#endif

/* Pure diffusion on the periodic cell, one block of trials (see kernel.walk_periodic).
 *   M scatterers laid out trial after trial (counts[b] each; block index i), pos [3, M] (µm, updated);
 *   frame f ≥ 1: pos_c[i] += sigma[f−1]·z (tdk_normals(key, f, c, ·)[i]), then pos −= L·rint(pos/L);
 *   per PSF group g: amplitude exp(−a_lat[g]·(x² + ry[g]·y²) − a_ax[g]·z²), 0 below log_tol (times
 *   taper_w of the exponent when tk ≠ 0); ry = 1 is the isotropic lateral PSF (y² not multiplied);
 *   per system s: acc[b, s, f, 0/1] += quantize(amp·cos/sin(2π·q[s]·z)).
 * Trial after trial, all frames: a trial's scatterers stay in the L1 cache.
 * Returns 0, or −1 if the scratch memory could not be allocated. */
CLONES int tdk_walk_periodic(int64_t M, int32_t n_trials, const int64_t *counts, float *pos, uint64_t key,
                             int32_t T, const float *sigma, const float *L, const float *inv_L, int32_t G,
                             const float *a_lat, const float *a_ax, const float *ry, int32_t S,
                             const int32_t *group_of, const float *q, float log_tol, float e0, float tk,
                             int64_t *acc) {
    int64_t nmax = 1;
    for (int32_t b = 0; b < n_trials; b++) nmax = counts[b] > nmax ? counts[b] : nmax;
    float *z = malloc(sizeof(float) * (size_t)(nmax + 4));
    float *amp = malloc(sizeof(float) * (size_t)(3 * nmax + 3));
    if (!z || !amp) { free(z); free(amp); return -1; }
    float *ka = amp + nmax + 1, *kz = amp + 2 * nmax + 2;
    int64_t i0 = 0;
    for (int32_t b = 0; b < n_trials; b++) {
        int64_t n = counts[b], i1 = i0 + n;
        float *px = pos + i0, *py = pos + M + i0, *pz = pos + 2 * M + i0;
        for (int32_t f = 0; f < T; f++) {
            if (f > 0 && n > 0) {
                float sg = sigma[f - 1];
                int64_t q0 = i0 >> 1, q1 = (i1 + 1) >> 1, off = i0 & 1;
                for (int32_t c = 0; c < 3; c++) {
                    float *p = pos + c * M + i0;
                    float l = L[c], il = inv_L[c];
                    normal_pairs(key, f, c, q0, q1, z);
                    const float *zc = z + off;
                    for (int64_t i = 0; i < n; i++) {
                        float v = p[i] + zc[i] * sg;
                        float w = rint_m(v * il);
                        p[i] = v - w * l;
                    }
                }
            }
            for (int32_t g = 0; g < G; g++) {
                float al = a_lat[g], az = a_ax[g], yr = ry[g];
                if (yr == 1.0f) {
                    for (int64_t i = 0; i < n; i++) {
                        float r2 = px[i] * px[i] + py[i] * py[i];
                        amp[i] = r2 * -al - (pz[i] * pz[i]) * az; /* the exponent, for now */
                    }
                } else {
                    for (int64_t i = 0; i < n; i++) {
                        float r2 = px[i] * px[i] + (py[i] * py[i]) * yr;
                        amp[i] = r2 * -al - (pz[i] * pz[i]) * az;
                    }
                }
                /* most of the cell lies outside the PSF: only the scatterers above the tolerance add
                 * anything (the others add exactly 0), so amplitudes and phases are evaluated on those */
                int64_t k = compact(n, amp, pz, log_tol, ka, kz);
                if (tk == 0.0f) {
                    for (int64_t i = 0; i < k; i++) ka[i] = exp_neg(ka[i]);
                } else {
                    for (int64_t i = 0; i < k; i++) ka[i] = exp_neg(ka[i]) * taper_w(ka[i], e0, tk);
                }
                for (int32_t s = 0; s < S; s++) {
                    if (group_of[s] != g) continue;
                    float qs = q[s];
                    int64_t re = 0, im = 0;
                    for (int64_t i = 0; i < k; i++) {
                        float sn, cs;
                        sincos_turns(kz[i] * qs, &sn, &cs);
                        re += quantize(ka[i] * cs);
                        im += quantize(ka[i] * sn);
                    }
                    int64_t *o = acc + (((int64_t)b * S + s) * T + f) * 2;
                    o[0] = re;
                    o[1] = im;
                }
            }
        }
        i0 = i1;
    }
    free(z);
    free(amp);
    return 0;
}

/* The field of k straight paths at T frames: the exponent e + a2·τ² and the phase φ + ω·τ (turns) at
 * τ = t_f − t*, counted where both the exponent and e are ≥ log_tol; out[2f], out[2f+1] = Σ quantize(
 * exp(exponent)·cos/sin(2π·phase)), the amplitude times taper_w(exponent) when `taper` (a constant at
 * each call, so the compiler keeps the hard loop as it was). Dense over the paths (one vector loop per frame). */
static inline void dense_paths(int64_t k, const float *e, const float *a2, const float *ts, const float *ph,
                               const float *om, int32_t T, const float *times, float log_tol, const int taper,
                               float e0, float tk, int64_t *out) {
    for (int32_t f = 0; f < T; f++) {
        float t = times[f];
        int64_t re = 0, im = 0;
        for (int64_t c = 0; c < k; c++) {
            float tau = t - ts[c];
            float ex = (tau * tau) * a2[c] + e[c];
            float amp = (ex >= log_tol && e[c] >= log_tol) ? exp_neg(ex) : 0.0f;
            if (taper) amp = amp * taper_w(ex, e0, tk);
            float sn, cs;
            sincos_turns(tau * om[c] + ph[c], &sn, &cs);
            re += quantize(amp * cs);
            im += quantize(amp * sn);
        }
        out[2 * f] = re;
        out[2 * f + 1] = im;
    }
}

/* Straight paths from their float32 coefficients (see kernel.eval_straight): C slots per trial,
 * acc [n_trials, T, 2]. */
CLONES void tdk_eval_straight(int32_t n_trials, int64_t C, const float *e, const float *a2, const float *t_star,
                              const float *phi, const float *omega, int32_t T, const float *times, float log_tol,
                              float e0, float tk, int64_t *acc) {
    for (int32_t b = 0; b < n_trials; b++) {
        int64_t o = (int64_t)b * C;
        int64_t *out = acc + (int64_t)b * T * 2;
        if (tk == 0.0f)
            dense_paths(C, e + o, a2 + o, t_star + o, phi + o, omega + o, T, times, log_tol, 0, e0, tk, out);
        else
            dense_paths(C, e + o, a2 + o, t_star + o, phi + o, omega + o, T, times, log_tol, 1, e0, tk, out);
    }
}

/* ---- straight paths from their draws (see kernel.drift_paths and kernel.path_fields) ---- */

#define FAR_UM 1.0e6 /* position of unused slots: the PSF amplitude there is exactly 0 */

/* A uniform on [0, 1) with 24 bits: SplitMix64 of `key` at the counter (stream, trial, slot, component). */
static inline float uniform24(uint64_t key, uint64_t stream, uint64_t trial, uint64_t slot, uint64_t comp) {
    uint64_t h = splitmix64(key, (stream << 56) | (trial << 48) | (slot << 8) | comp);
    return (float)(uint32_t)(h >> 40) * 0x1p-24f;
}

/* Uniform positions of a block's M scatterers in the cell |x_c| ≤ half[c]: pos[c, i] = (2u − 1)·half[c],
 * u = uniform24(key, 6, c, i, 0) (float32). */
CLONES void tdk_uniform_cell(uint64_t key, int64_t M, const float *half, float *pos) {
    for (int c = 0; c < 3; c++) {
        float h = half[c];
        for (int64_t i = 0; i < M; i++) pos[c * M + i] = (uniform24(key, 6, (uint64_t)c, (uint64_t)i, 0) * 2.0f - 1.0f) * h;
    }
}

/* Unit vector from two uniforms: law 0 isotropic (cos θ = 2u₀ − 1), law 1 uniform angles (θ = π·u₀);
 * azimuth 2π·u₁ (physics.md §10.2). */
static inline void direction(int32_t law, float u0, float u1, double *d) {
    double mu;
    if (law == 0) {
        mu = 2.0 * (double)u0 - 1.0;
    } else {
        float s, c;
        sincos_turns(u0 * 0.5f, &s, &c);
        mu = (double)c;
    }
    double st2 = 1.0 - mu * mu;
    double st = sqrt(st2 > 0.0 ? st2 : 0.0);
    float sp, cp;
    sincos_turns(u1, &sp, &cp);
    d[0] = st * (double)cp;
    d[1] = st * (double)sp;
    d[2] = mu;
}

/* Velocities (µm/s) of slots 0..n−1 of a stream: flow + Σ_k speed_k·direction_k, the direction of
 * ballistic component k from the uniforms of components 2k and 2k+1 (one vector pass per component). */
static inline void velocities(uint64_t key, uint64_t stream, uint64_t tb, int64_t n, const double *flow, int32_t K,
                       const double *speed, const int32_t *law, double *vx, double *vy, double *vz) {
    for (int64_t j = 0; j < n; j++) {
        vx[j] = flow[0];
        vy[j] = flow[1];
        vz[j] = flow[2];
    }
    for (int32_t k = 0; k < K; k++) {
        double sp = speed[k];
        int32_t lw = law[k];
        for (int64_t j = 0; j < n; j++) {
            double d[3];
            direction(lw, uniform24(key, stream, tb, (uint64_t)j, 2 * k), uniform24(key, stream, tb, (uint64_t)j, 2 * k + 1), d);
            vx[j] = vx[j] + sp * d[0];
            vy[j] = vy[j] + sp * d[1];
            vz[j] = vz[j] + sp * d[2];
        }
    }
}

/* u^(1/3) for u in [0, 1]: a float32 guess, then two Newton steps in double. */
static inline double cbrt_unit(float u) {
    if (u == 0.0f) return 0.0;
    double y = (double)exp_neg(log_pos(u) * 0x1.555556p-2f);
    double y2 = y * y;
    y = y - (y2 * y - (double)u) / (y2 * 3.0);
    y2 = y * y;
    return y - (y2 * y - (double)u) / (y2 * 3.0);
}

/* The straight paths of N trials (see kernel.drift_paths). Outputs component-major p, v [3, N, cap] and
 * t_ref [N, cap], count [N]; slots past the count are far away and still. Each trial runs in vector
 * passes: initial paths, proposal velocities and acceptance, then the entry geometry of the accepted.
 * Returns 0, −1 when scratch memory is missing, or 1 + the trial whose accepted entrants exceed E. */
CLONES int tdk_drift_paths(int32_t N, const uint64_t *keys, const int64_t *n0, const int64_t *n_prop, const double *H,
                           const double *flow, int32_t K, const double *speed, const int32_t *law, double w_max,
                           double T, int64_t E, int64_t cap, double *p, double *v, double *t_ref, int64_t *count) {
    int64_t P = 1;
    for (int32_t b = 0; b < N; b++) P = n_prop[b] > P ? n_prop[b] : P;
    double *sv = malloc(sizeof(double) * (size_t)(4 * P));
    int64_t *list = malloc(sizeof(int64_t) * (size_t)P);
    if (!sv || !list) { free(sv); free(list); return -1; }
    double *svx = sv, *svy = sv + P, *svz = sv + 2 * P;
    unsigned char *acc = (unsigned char *)(sv + 3 * P);
    int64_t NC = (int64_t)N * cap;
    double *px = p, *py = p + NC, *pz = p + 2 * NC, *vx = v, *vy = v + NC, *vz = v + 2 * NC;
    for (int32_t b = 0; b < N; b++) {
        uint64_t key = keys[b / 64], tb = (uint64_t)(b % 64);
        int64_t base = (int64_t)b * cap, m0 = n0[b], mp = n_prop[b];
        for (int64_t j = 0; j < m0; j++) {
            double d[3];
            direction(0, uniform24(key, 1, tb, (uint64_t)j, 0), uniform24(key, 1, tb, (uint64_t)j, 1), d);
            double r = cbrt_unit(uniform24(key, 1, tb, (uint64_t)j, 2));
            px[base + j] = (d[0] * r) * H[0];
            py[base + j] = (d[1] * r) * H[1];
            pz[base + j] = (d[2] * r) * H[2];
            t_ref[base + j] = 0.0;
        }
        velocities(key, 2, tb, m0, flow, K, speed, law, vx + base, vy + base, vz + base);
        velocities(key, 3, tb, mp, flow, K, speed, law, svx, svy, svz);
        for (int64_t j = 0; j < mp; j++) {
            double wx = svx[j] / H[0], wy = svy[j] / H[1], wz = svz[j] / H[2];
            double wn = sqrt(wx * wx + wy * wy + wz * wz);
            acc[j] = (double)uniform24(key, 4, tb, (uint64_t)j, 0) * w_max < wn;
        }
        int64_t na = 0;
        for (int64_t j = 0; j < mp; j++) {
            list[na] = j;
            na += acc[j];
        }
        if (na > E) { free(sv); free(list); return 1 + b; }
        if (m0 + na > cap) { free(sv); free(list); return 1 + b; }
        for (int64_t m = 0; m < na; m++) {
            int64_t j = list[m], k = base + m0 + m;
            double vel[3] = {svx[j], svy[j], svz[j]};
            double wx = vel[0] / H[0], wy = vel[1] / H[1], wz = vel[2] / H[2];
            double wn = sqrt(wx * wx + wy * wy + wz * wz);
            double nx = wx / wn, ny = wy / wn, nz = wz / wn;
            double sgn = nz >= 0.0 ? 1.0 : -1.0;
            double a = -1.0 / (sgn + nz);
            double bb = nx * ny * a;
            double e1x = 1.0 + sgn * nx * nx * a, e1y = sgn * bb, e1z = -sgn * nx;
            double e2x = bb, e2y = sgn + ny * ny * a, e2z = -ny;
            float g0 = uniform24(key, 5, tb, (uint64_t)j, 0), g1 = uniform24(key, 5, tb, (uint64_t)j, 1);
            float g2 = uniform24(key, 5, tb, (uint64_t)j, 2);
            double rad = sqrt((double)g0), depth = sqrt(1.0 - (double)g0);
            float s, c;
            sincos_turns(g1, &s, &c);
            double c1 = rad * (double)c, c2 = rad * (double)s;
            px[k] = ((c1 * e1x + c2 * e2x) - depth * nx) * H[0];
            py[k] = ((c1 * e1y + c2 * e2y) - depth * ny) * H[1];
            pz[k] = ((c1 * e1z + c2 * e2z) - depth * nz) * H[2];
            vx[k] = vel[0];
            vy[k] = vel[1];
            vz[k] = vel[2];
            t_ref[k] = (double)g2 * T;
        }
        count[b] = m0 + na;
        for (int64_t k = base + m0 + na; k < base + cap; k++) {
            px[k] = py[k] = pz[k] = FAR_UM;
            vx[k] = vy[k] = vz[k] = 0.0;
            t_ref[k] = 0.0;
        }
    }
    free(sv);
    free(list);
    return 0;
}

/* −(a_lat·(x·xx + (y·yy)·ry)) − a_ax·(z·zz); ry = 1 (the isotropic lateral PSF) changes no bit */
static inline double norm_w(double al, double az, double ry, double x, double y, double z, double xx, double yy,
                            double zz) {
    return -(al * (x * xx + (y * yy) * ry)) - az * (z * zz);
}

/* Fields of straight paths for S systems (see kernel.path_fields): per path the float64 coefficients
 * about the closest approach (exponent e* + a2·τ², phase φ* + ω·τ in turns), rounded to float32, then
 * the float32 evaluation of tdk_eval_straight. p, v [3, N, C]; acc [N, S, T, 2]. Returns 0 or −1. */
CLONES int tdk_path_fields(int32_t N, int64_t C, const double *p, const double *v, const double *t_ref,
                           int64_t comp_stride, int64_t row_stride, int32_t S, const double *q, const double *a_lat,
                           const double *a_ax, const double *ry, int32_t T, const float *times, float log_tol,
                           float e0, float tk, int64_t *acc) {
    float *w = malloc(sizeof(float) * (size_t)(10 * C + 2));
    unsigned char *vis = malloc((size_t)C + 1);
    if (!w || !vis) { free(w); free(vis); return -1; }
    float *fe = w, *fa = w + C, *ft = w + 2 * C, *fp = w + 3 * C, *fo = w + 4 * C;
    float *ke = w + 5 * C, *ka = w + 6 * C, *kt = w + 7 * C, *kp = w + 8 * C, *ko = w + 9 * C;
    int64_t NC = comp_stride;
    for (int32_t b = 0; b < N; b++) {
        for (int32_t s = 0; s < S; s++) {
            double al = a_lat[s], az = a_ax[s], yr = ry[s], qs = q[s];
            for (int64_t c = 0; c < C; c++) {
                int64_t i = (int64_t)b * row_stride + c;
                double px = p[i], py = p[NC + i], pz = p[2 * NC + i];
                int moving = px < 0.5 * FAR_UM;
                double vx = moving ? v[i] : 0.0, vy = moving ? v[NC + i] : 0.0, vz = moving ? v[2 * NC + i] : 0.0;
                double a2 = norm_w(al, az, yr, vx, vy, vz, vx, vy, vz);
                double shift = a2 != 0.0 ? -(norm_w(al, az, yr, px, py, pz, vx, vy, vz) / a2) : 0.0;
                double rx = px + vx * shift, ryy = py + vy * shift, rz = pz + vz * shift;
                double x = rz * qs;
                fe[c] = (float)norm_w(al, az, yr, rx, ryy, rz, rx, ryy, rz);
                fa[c] = (float)a2;
                ft[c] = (float)(t_ref[i] + shift);
                fp[c] = (float)(x - floor(x));
                fo[c] = (float)(vz * qs);
                vis[c] = 0;
            }
            /* a path whose exponent is below the tolerance at every frame adds exactly 0: skip it */
            for (int32_t f = 0; f < T; f++) {
                float t = times[f];
                for (int64_t c = 0; c < C; c++) {
                    float tau = t - ft[c];
                    float ex = (tau * tau) * fa[c] + fe[c];
                    vis[c] |= (ex >= log_tol) & (fe[c] >= log_tol);
                }
            }
            int64_t k = 0;
            for (int64_t c = 0; c < C; c++) {
                if (!vis[c]) continue;
                ke[k] = fe[c];
                ka[k] = fa[c];
                kt[k] = ft[c];
                kp[k] = fp[c];
                ko[k] = fo[c];
                k++;
            }
            int64_t *out = acc + ((int64_t)b * S + s) * T * 2;
            if (tk == 0.0f)
                dense_paths(k, ke, ka, kt, kp, ko, T, times, log_tol, 0, e0, tk, out);
            else
                dense_paths(k, ke, ka, kt, kp, ko, T, times, log_tol, 1, e0, tk, out);
        }
    }
    free(w);
    free(vis);
    return 0;
}

#ifndef TORCHDOCT_NO_PYTHON
/* A Python module only so that setuptools builds and installs the library; it is used through ctypes.
 * (kernel.py can also build it as a plain shared library, with TORCHDOCT_NO_PYTHON defined.) */
static struct PyModuleDef kernel_module = {PyModuleDef_HEAD_INIT, "_kernel",
                                           "Fused float32 simulator kernels (used through ctypes).", -1, NULL};

PyMODINIT_FUNC PyInit__kernel(void) { return PyModule_Create(&kernel_module); }
#endif
