/* Fused CPU kernels of the radiance-field hot path (see aoi3d/field/native.py).
 *
 * C99 with GCC/Clang vector extensions, no Python or torch headers: compiled at first use
 * with the system C compiler and called through ctypes on float32 / int64 tensor memory
 * (contiguous). Each kernel is the fused form of a chain of torch operations whose result it
 * reproduces up to float rounding order; the torch chains remain the reference (and the
 * fallback).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Four floats, one grid row (raw density, raw RGB): GCC/Clang vector extensions, so that a
 * row is read, scaled and added as one value on any target (SSE on x86-64; only x86-64 was
 * built and measured here). */
typedef float row4 __attribute__((vector_size(16)));

static inline row4 load_row(const float *p) {
    row4 r;
    memcpy(&r, p, sizeof r);
    return r;
}

static inline void store_row(float *p, row4 r) { memcpy(p, &r, sizeof r); }

/* The 8 corner rows and trilinear weights of a world point in a grid of shape (nx, ny, nz)
 * vertices spanning the box from lo, factor = (n - 1) / (hi - lo) per axis; rows are
 * row-major (z minor), corner k takes the upper vertex along x, y, z for bits 2, 1, 0 of k
 * (aoi3d.field.encodings.corner_rows). Coordinates are clamped to the grid. */
static inline void corners(const float *p, const float *lo, const float *factor,
                           const int64_t *shape, int64_t *rows, float *w) {
    int64_t base[3];
    float frac[3];
    for (int d = 0; d < 3; d++) {
        float n1 = (float)(shape[d] - 1);
        float c = (p[d] - lo[d]) * factor[d];
        c = c < 0.0f ? 0.0f : (c > n1 ? n1 : c);
        float b = (float)(int64_t)c;  /* floor: c >= 0 */
        if (b > n1 - 1.0f) b = n1 - 1.0f;
        base[d] = (int64_t)b;
        frac[d] = c - b;
    }
    int64_t sy = shape[2], sx = shape[1] * shape[2];
    int64_t r0 = base[0] * sx + base[1] * sy + base[2];
    for (int k = 0; k < 8; k++) {
        int ux = (k >> 2) & 1, uy = (k >> 1) & 1, uz = k & 1;
        rows[k] = r0 + (ux ? sx : 0) + (uy ? sy : 0) + (uz ? 1 : 0);
        float wx = ux ? frac[0] : 1.0f - frac[0];
        float wy = uy ? frac[1] : 1.0f - frac[1];
        float wz = uz ? frac[2] : 1.0f - frac[2];
        w[k] = (wx * wy) * wz;
    }
}

/* exp(x) in float32 to about 1 ulp (Cephes' expf: 2^n · e^r, |r| ≤ ln2/2, degree-7
 * polynomial), in arithmetic only, so that loops over it vectorise. */
static inline float exp_approx(float x) {
    x = x > 88.3762626647949f ? 88.3762626647949f : x;
    x = x < -87.3365447505531f ? -87.3365447505531f : x;
    float fx = x * 1.44269504088896341f + 0.5f;
    int32_t n = (int32_t)fx;
    n -= (float)n > fx;  /* floor */
    float nf = (float)n;
    float r = x - nf * 0.693359375f + nf * 2.12194440e-4f;
    float r2 = r * r;
    float y = 1.9875691500e-4f;
    y = y * r + 1.3981999507e-3f;
    y = y * r + 8.3334519073e-3f;
    y = y * r + 4.1665795894e-2f;
    y = y * r + 1.6666665459e-1f;
    y = y * r + 5.0000001201e-1f;
    y = y * r2 + r + 1.0f;
    union { int32_t i; float f; } scale = {.i = (n + 127) << 23};
    return y * scale.f;
}

/* expm1(x) = e^x − 1 in float32 without cancellation near 0: its Taylor polynomial of degree 8
 * for |x| < 0.5 (truncation below 2e-8 relative), exp_approx(x) − 1 beyond; in arithmetic
 * only, so that loops over it vectorise. */
static inline float expm1_approx(float x) {
    float p = 1.0f / 40320.0f;
    p = p * x + 1.0f / 5040.0f;
    p = p * x + 1.0f / 720.0f;
    p = p * x + 1.0f / 120.0f;
    p = p * x + 1.0f / 24.0f;
    p = p * x + 1.0f / 6.0f;
    p = p * x + 0.5f;
    p = p * x + 1.0f;
    float small = x * p;
    float large = exp_approx(x) - 1.0f;
    return (x > -0.5f && x < 0.5f) ? small : large;
}

/* log(y) in float32 to about 1 ulp for normal y > 0 (Cephes' logf), in arithmetic only. */
static inline float log_approx(float y) {
    union { float f; int32_t i; } u = {.f = y};
    int32_t e = ((u.i >> 23) & 0xff) - 126;
    u.i = (u.i & (int32_t)0x807fffff) | 0x3f000000;  /* mantissa in [0.5, 1) */
    float m = u.f;
    float small = m < 0.707106781186547524f ? 1.0f : 0.0f;  /* then use 2m, e − 1 */
    m = (m - 1.0f) + small * m;
    float z2 = m * m;
    float p = 7.0376836292e-2f;
    p = p * m - 1.1514610310e-1f;
    p = p * m + 1.1676998740e-1f;
    p = p * m - 1.2420140846e-1f;
    p = p * m + 1.4249322787e-1f;
    p = p * m - 1.6668057665e-1f;
    p = p * m + 2.0000714765e-1f;
    p = p * m - 2.4999993993e-1f;
    p = p * m + 3.3333331174e-1f;
    float ef = (float)e - small;
    float r = p * m * z2;
    r += ef * -2.12194440e-4f;
    r += -0.5f * z2;
    r = m + r;
    return r + ef * 0.693359375f;
}

/* The grid backend's query: trilinear interpolation of the table (N, 4) (raw density, raw
 * RGB) at points (P, 3), then sigma = softplus(raw density), rgb = sigmoid(raw RGB) (in
 * loops over exp_approx and log_approx after the gather, which vectorise). Writes sigma (P), rgb (P, 3)
 * and sigma_grad (P): d sigma / d raw density, for the backward. */
void grid_query_forward(const float *table, const float *points, int64_t n_points,
                        const float *lo, const float *factor, const int64_t *shape,
                        float *sigma, float *rgb, float *sigma_grad) {
    int64_t rows[8];
    float w[8];
    for (int64_t i = 0; i < n_points; i++) {
        corners(points + 3 * i, lo, factor, shape, rows, w);
        row4 acc = {0.0f, 0.0f, 0.0f, 0.0f};
        for (int k = 0; k < 8; k++) acc += w[k] * load_row(table + 4 * rows[k]);
        sigma[i] = acc[0];
        for (int c = 0; c < 3; c++) rgb[3 * i + c] = acc[1 + c];
    }
    for (int64_t j = 0; j < 3 * n_points; j++) rgb[j] = 1.0f / (1.0f + exp_approx(-rgb[j]));
    for (int64_t i = 0; i < n_points; i++) {
        /* softplus = log1p(e^x) = log(y) + (z − (y − 1)) / y with z = e^x, y = 1 + z (the
         * correction restores what 1 + z rounds away); linear above torch's threshold 20 */
        float x = sigma[i];
        float z = exp_approx(x < 20.0f ? x : 20.0f);
        float y = 1.0f + z;
        float softplus = log_approx(y) + (z - (y - 1.0f)) / y;
        float linear = x > 20.0f ? 1.0f : 0.0f;
        sigma[i] = linear * x + (1.0f - linear) * softplus;
        sigma_grad[i] = linear + (1.0f - linear) * (z / y);
    }
}

/* Its backward: the gradient of the table, row-sparse. grad_sigma (P) and grad_rgb (P, 3)
 * (either may be NULL: zero) go back through the activations and are scattered into the
 * workspace dense (N, 4), zero on entry, marking touched (N) bytes, zero on entry; then the
 * touched rows are compacted in increasing order into out_rows (≤ N) and out_values
 * (≤ N, 4), and the workspace is left zero again. Returns the number of touched rows. */
int64_t grid_query_backward(const float *points, int64_t n_points, const float *lo,
                            const float *factor, const int64_t *shape, const float *grad_sigma,
                            const float *grad_rgb, const float *rgb, const float *sigma_grad,
                            int64_t n_rows, float *dense, uint8_t *touched, int64_t *out_rows,
                            float *out_values) {
    int64_t rows[8];
    float w[8];
    for (int64_t i = 0; i < n_points; i++) {
        row4 g;
        g[0] = grad_sigma ? grad_sigma[i] * sigma_grad[i] : 0.0f;
        for (int c = 0; c < 3; c++) {
            float s = rgb[3 * i + c];
            g[1 + c] = grad_rgb ? grad_rgb[3 * i + c] * (s * (1.0f - s)) : 0.0f;
        }
        corners(points + 3 * i, lo, factor, shape, rows, w);
        for (int k = 0; k < 8; k++) {
            float *row = dense + 4 * rows[k];
            store_row(row, load_row(row) + w[k] * g);
            touched[rows[k]] = 1;
        }
    }
    int64_t n = 0;
    for (int64_t r = 0; r < n_rows; r++) {
        if (!touched[r]) continue;
        out_rows[n] = r;
        memcpy(out_values + 4 * n, dense + 4 * r, 4 * sizeof(float));
        memset(dense + 4 * r, 0, 4 * sizeof(float));  /* left zero for the next call */
        touched[r] = 0;
        n++;
    }
    return n;
}

/* Volume rendering of packed samples (aoi3d.field.render.volume_render): sigma (P),
 * rgb (P, 3), deltas (P), ray_index (P) (the samples of a ray in order along it),
 * background (R, 3). Writes color (R, 3), transmittance (R), weights (P), alpha (P) and
 * before (P): the transmittance T_i in front of each sample (for the backward). Optical
 * depth is accumulated in double, its exponential taken in float. */
void volume_render_forward(const float *sigma, const float *rgb, const float *deltas,
                           const int64_t *ray_index, int64_t n_samples, const float *background,
                           int64_t n_rays, float *color, float *transmittance, float *weights,
                           float *alpha, float *before) {
    double *depth = calloc((size_t)(n_rays > 0 ? n_rays : 1), sizeof(double));
    memset(color, 0, (size_t)n_rays * 3 * sizeof(float));
    for (int64_t i = 0; i < n_samples; i++) alpha[i] = -expm1_approx(-(sigma[i] * deltas[i]));
    for (int64_t i = 0; i < n_samples; i++) {
        int64_t r = ray_index[i];
        float tau = sigma[i] * deltas[i];
        float a = alpha[i];
        float t = exp_approx(-(float)depth[r]);
        float wi = t * a;
        before[i] = t;
        weights[i] = wi;
        for (int c = 0; c < 3; c++) color[3 * r + c] += wi * rgb[3 * i + c];
        depth[r] += (double)tau;
    }
    for (int64_t r = 0; r < n_rays; r++) {
        float t = exp_approx(-(float)depth[r]);
        transmittance[r] = t;
        for (int c = 0; c < 3; c++) color[3 * r + c] += t * background[3 * r + c];
    }
    free(depth);
}

/* Its backward. grad_color (R, 3), grad_transmittance (R), grad_weights (P), grad_alpha (P)
 * (any may be NULL: zero). With w_i = T_i α_i, T_i = exp(−Σ_{j<i} τ_j), α_i = 1 − exp(−τ_i):
 *   dL/dτ_k = (g_w,k T_k + g_α,k)(1 − α_k) − Σ_{i>k, same ray} g_w,i w_i − g_T,N T_N,
 * with g_w,i = grad_weights_i + grad_color_r · c_i and g_T,N = grad_transmittance_r +
 * grad_color_r · background_r. Writes grad_sigma (P) = δ · dL/dτ, grad_rgb (P, 3) and
 * grad_background (R, 3). */
void volume_render_backward(const float *rgb, const float *deltas, const int64_t *ray_index,
                            int64_t n_samples, const float *background, int64_t n_rays,
                            const float *transmittance, const float *weights, const float *alpha,
                            const float *before, const float *grad_color,
                            const float *grad_transmittance, const float *grad_weights,
                            const float *grad_alpha, float *grad_sigma, float *grad_rgb,
                            float *grad_background) {
    double *suffix = calloc((size_t)(n_rays > 0 ? n_rays : 1), sizeof(double));
    float *g_end = malloc((size_t)(n_rays > 0 ? n_rays : 1) * sizeof(float));
    for (int64_t r = 0; r < n_rays; r++) {
        float g = grad_transmittance ? grad_transmittance[r] : 0.0f;
        for (int c = 0; c < 3; c++) {
            float gc = grad_color ? grad_color[3 * r + c] : 0.0f;
            g += gc * background[3 * r + c];
            grad_background[3 * r + c] = gc * transmittance[r];
        }
        g_end[r] = g * transmittance[r];
    }
    for (int64_t i = n_samples - 1; i >= 0; i--) {
        int64_t r = ray_index[i];
        float gw = grad_weights ? grad_weights[i] : 0.0f;
        for (int c = 0; c < 3; c++) {
            float gc = grad_color ? grad_color[3 * r + c] : 0.0f;
            gw += gc * rgb[3 * i + c];
            grad_rgb[3 * i + c] = gc * weights[i];
        }
        float ga = grad_alpha ? grad_alpha[i] : 0.0f;
        double gtau = (double)((gw * before[i] + ga) * (1.0f - alpha[i])) - suffix[r] - g_end[r];
        grad_sigma[i] = (float)gtau * deltas[i];
        suffix[r] += (double)gw * (double)weights[i];
    }
    free(suffix);
    free(g_end);
}

/* LazyAdam's update of the rows of a row-sparse gradient (aoi3d.field.optim.LazyAdam):
 * rows (n, increasing, unique) of param, exp_avg, exp_avg_sq (each (N, C)), gradient
 * values (n, C). m ← m + (g − m)(1 − β1); v ← β2 v + (1 − β2) g²;
 * p ← p − step_size · m / (√v / root_bias + eps), in torch's order of operations. Returns 0
 * (nothing done) when the rows are not increasing, else 1. */
int64_t lazy_adam_rows(float *param, float *exp_avg, float *exp_avg_sq, const int64_t *rows,
                       const float *values, int64_t n, int64_t columns, float beta1, float beta2,
                       float step_size, float root_bias, float eps) {
    for (int64_t i = 1; i < n; i++)
        if (rows[i] <= rows[i - 1]) return 0;  /* not coalesced: the caller sums rows first */
    float w1 = 1.0f - beta1, w2 = 1.0f - beta2;
    if (columns == 4) {  /* the grid's rows: one vector each, the same operations */
        for (int64_t i = 0; i < n; i++) {
            int64_t base = rows[i] * 4;
            row4 g = load_row(values + 4 * i);
            row4 m = load_row(exp_avg + base);
            m = m + w1 * (g - m);
            row4 v = load_row(exp_avg_sq + base) * beta2 + w2 * g * g;
            store_row(exp_avg + base, m);
            store_row(exp_avg_sq + base, v);
            row4 root;
            for (int c = 0; c < 4; c++) root[c] = sqrtf(v[c]);
            row4 denom = root / root_bias + eps;
            store_row(param + base, load_row(param + base) + (m / denom) * -step_size);
        }
        return 1;
    }
    for (int64_t i = 0; i < n; i++) {
        int64_t base = rows[i] * columns;
        for (int64_t c = 0; c < columns; c++) {
            float g = values[i * columns + c];
            float m = exp_avg[base + c];
            m = m + w1 * (g - m);
            float v = exp_avg_sq[base + c] * beta2 + w2 * g * g;
            exp_avg[base + c] = m;
            exp_avg_sq[base + c] = v;
            float denom = sqrtf(v) / root_bias + eps;
            param[base + c] += (m / denom) * -step_size;
        }
    }
    return 1;
}

/* The uniform sampler (aoi3d.field.rays.sample_uniform), in two calls. Count: the samples of
 * each ray (counts, R) for chords max(t_far − t_near, 0) cut at step, from at most n_steps
 * intervals; returns their total. Fill: points (P, 3), deltas (P), ray_index (P) ray after
 * ray, the sample at fraction jitter[r] (0.5 when jitter is NULL) of its clipped interval,
 * in torch's order of operations. */
int64_t sample_uniform_count(const float *t_near, const float *t_far, int64_t n_rays,
                             float step, int64_t n_steps, int64_t *counts) {
    int64_t total = 0;
    for (int64_t r = 0; r < n_rays; r++) {
        float chord = t_far[r] - t_near[r];
        chord = chord > 0.0f ? chord : 0.0f;
        int64_t k = 0;
        while (k < n_steps && chord - (float)k * step > 0.0f) k++;
        counts[r] = k;
        total += k;
    }
    return total;
}

void sample_uniform_fill(const float *origins, const float *dirs, const float *t_near,
                         const float *t_far, const float *jitter, int64_t n_rays, float step,
                         const int64_t *counts, float *points, float *deltas,
                         int64_t *ray_index) {
    int64_t j = 0;
    for (int64_t r = 0; r < n_rays; r++) {
        float chord = t_far[r] - t_near[r];
        chord = chord > 0.0f ? chord : 0.0f;
        float frac = jitter ? jitter[r] : 0.5f;
        for (int64_t k = 0; k < counts[r]; k++, j++) {
            float start = (float)k * step;
            float remaining = chord - start;
            float delta = remaining < step ? remaining : step;
            float t = (t_near[r] + start) + frac * delta;
            for (int c = 0; c < 3; c++) points[3 * j + c] = origins[3 * r + c] + dirs[3 * r + c] * t;
            deltas[j] = delta;
            ray_index[j] = r;
        }
    }
}

/* Adam's update of a whole tensor of n values from a dense gradient, as LazyAdam's dense path
 * does it (same formulas as lazy_adam_rows). */
void adam_dense(float *param, float *exp_avg, float *exp_avg_sq, const float *grad, int64_t n,
                float beta1, float beta2, float step_size, float root_bias, float eps) {
    float w1 = 1.0f - beta1, w2 = 1.0f - beta2;
    for (int64_t i = 0; i < n; i++) {
        float g = grad[i];
        float m = exp_avg[i] + w1 * (g - exp_avg[i]);
        float v = exp_avg_sq[i] * beta2 + w2 * g * g;
        exp_avg[i] = m;
        exp_avg_sq[i] = v;
        param[i] += (m / (sqrtf(v) / root_bias + eps)) * -step_size;
    }
}

/* DVGO's per-sample colour loss, summed: Σ_i w_i ‖c_i − target[ray_i]‖² over samples with
 * colours c (P, 3), weights w (P), their rays (P) and the rays' target colours (R, 3); the
 * sum accumulated in double. */
double weighted_colour_error_forward(const float *colours, const float *weights,
                                     const int64_t *ray_index, int64_t n_samples,
                                     const float *target) {
    double total = 0.0;
    for (int64_t i = 0; i < n_samples; i++) {
        const float *t = target + 3 * ray_index[i];
        float err = 0.0f;
        for (int c = 0; c < 3; c++) {
            float d = colours[3 * i + c] - t[c];
            err += d * d;
        }
        total += (double)(weights[i] * err);
    }
    return total;
}

/* Its backward for the upstream gradient g: grad_colours (P, 3), grad_weights (P). */
void weighted_colour_error_backward(const float *colours, const float *weights,
                                    const int64_t *ray_index, int64_t n_samples,
                                    const float *target, float g, float *grad_colours,
                                    float *grad_weights) {
    for (int64_t i = 0; i < n_samples; i++) {
        const float *t = target + 3 * ray_index[i];
        float err = 0.0f;
        float gw = g * weights[i] * 2.0f;
        for (int c = 0; c < 3; c++) {
            float d = colours[3 * i + c] - t[c];
            err += d * d;
            grad_colours[3 * i + c] = gw * d;
        }
        grad_weights[i] = g * err;
    }
}

/* The lat-long background (aoi3d.field.background.latlong_background): the four map cells
 * around each direction and their bilinear weights. */
static inline void latlong_cell(const float *dir, int64_t up, int64_t rows, int64_t cols,
                                int64_t *idx, float *w) {
    const float pi = 3.14159265358979323846f;
    int64_t a = (up + 1) % 3, b = (up + 2) % 3;
    float du = dir[up];
    du = du < -1.0f ? -1.0f : (du > 1.0f ? 1.0f : du);
    float polar = acosf(du) / pi;
    float azimuth = atan2f(dir[b], dir[a]) / (2.0f * pi);
    azimuth = azimuth - floorf(azimuth);  /* % 1.0 */
    float r = polar * (float)(rows - 1);
    float r0 = floorf(r);
    r0 = r0 < 0.0f ? 0.0f : (r0 > (float)(rows - 2) ? (float)(rows - 2) : r0);
    float fr = r - r0;
    float col = azimuth * (float)cols;
    float c0f = floorf(col);
    float fc = col - c0f;
    int64_t c0 = ((int64_t)c0f % cols + cols) % cols;
    int64_t c1 = (c0 + 1) % cols;
    int64_t i0 = (int64_t)r0;
    idx[0] = i0 * cols + c0;
    idx[1] = i0 * cols + c1;
    idx[2] = (i0 + 1) * cols + c0;
    idx[3] = (i0 + 1) * cols + c1;
    w[0] = (1.0f - fc) * (1.0f - fr);
    w[1] = fc * (1.0f - fr);
    w[2] = (1.0f - fc) * fr;
    w[3] = fc * fr;
}

/* Colours (R, 3) = sigmoid of the bilinear sample of the raw map env (rows, cols, 3) in the
 * unit directions dirs (R, 3) around axis up. */
void latlong_forward(const float *env, int64_t rows, int64_t cols, const float *dirs,
                     int64_t n_rays, int64_t up, float *out) {
    int64_t idx[4];
    float w[4];
    for (int64_t r = 0; r < n_rays; r++) {
        latlong_cell(dirs + 3 * r, up, rows, cols, idx, w);
        for (int c = 0; c < 3; c++) {
            float top = env[3 * idx[0] + c] * w[0] + env[3 * idx[1] + c] * w[1];
            float bottom = env[3 * idx[2] + c] * w[2] + env[3 * idx[3] + c] * w[3];
            out[3 * r + c] = 1.0f / (1.0f + expf(-(top + bottom)));
        }
    }
}

/* Its backward: grad_env (rows, cols, 3), zero on entry, from grad_out (R, 3) and out. */
void latlong_backward(int64_t rows, int64_t cols, const float *dirs, int64_t n_rays, int64_t up,
                      const float *out, const float *grad_out, float *grad_env) {
    int64_t idx[4];
    float w[4];
    for (int64_t r = 0; r < n_rays; r++) {
        latlong_cell(dirs + 3 * r, up, rows, cols, idx, w);
        for (int c = 0; c < 3; c++) {
            float s = out[3 * r + c];
            float g = grad_out[3 * r + c] * (s * (1.0f - s));
            for (int k = 0; k < 4; k++) grad_env[3 * idx[k] + c] += g * w[k];
        }
    }
}

/* The flow backend's kernels (trilinear interpolation without activations, its gradient
 * with respect to the point, a dense scatter): in their own file, one library. */
#include "_native_flow.c"
