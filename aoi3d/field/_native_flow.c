/* Fused kernels of the ``flow`` backend (aoi3d/field/flow.py, aoi3d/field/native_flow.py):
 * a vertex grid of four raw columns interpolated trilinearly without activations (the
 * canonical grid resampled along the flow), the warp of sample points by the velocity grid,
 * the grid's backward with the gradient with respect to each point (what moves a sample
 * along the flow), and the scatter of per-point gradients into a dense table. Included at the end of _native.c (one
 * library; its row4 helpers are shared); the torch code of aoi3d/field/flow.py is the
 * reference and the fallback. */

/* As corners() of _native.c, plus each axis's fraction and whether the point lies inside
 * the grid along it (inside: the clamp passes the gradient, as torch's clamp does). */
static inline void corners_frac(const float *p, const float *lo, const float *factor,
                                const int64_t *shape, int64_t *rows, float *w, float *frac,
                                float *inside) {
    int64_t base[3];
    for (int d = 0; d < 3; d++) {
        float n1 = (float)(shape[d] - 1);
        float c = (p[d] - lo[d]) * factor[d];
        inside[d] = (c >= 0.0f && c <= n1) ? 1.0f : 0.0f;
        c = c < 0.0f ? 0.0f : (c > n1 ? n1 : c);
        float b = (float)(int64_t)c;
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

/* out (P, 4): the trilinear interpolation of table (N, 4) at points (P, 3), raw. */
void trilinear4_forward(const float *table, const float *points, int64_t n_points,
                        const float *lo, const float *factor, const int64_t *shape,
                        float *out) {
    int64_t rows[8];
    float w[8];
    for (int64_t i = 0; i < n_points; i++) {
        corners(points + 3 * i, lo, factor, shape, rows, w);
        row4 acc = {0.0f, 0.0f, 0.0f, 0.0f};
        for (int k = 0; k < 8; k++) acc += w[k] * load_row(table + 4 * rows[k]);
        store_row(out + 4 * i, acc);
    }
}

/* grad_table (N, 4) += the trilinear scatter of g (P, 4) at points (P, 3). */
void trilinear4_scatter(const float *points, int64_t n_points, const float *lo,
                        const float *factor, const int64_t *shape, const float *g,
                        float *grad_table) {
    int64_t rows[8];
    float w[8];
    for (int64_t i = 0; i < n_points; i++) {
        corners(points + 3 * i, lo, factor, shape, rows, w);
        row4 gi = load_row(g + 4 * i);
        for (int k = 0; k < 8; k++) {
            float *row = grad_table + 4 * rows[k];
            store_row(row, load_row(row) + w[k] * gi);
        }
    }
}

/* The grid's backward (grid_query_backward of _native.c: the table's row-sparse gradient from
 * those of sigma (P) and rgb (P, 3) through the activations), and in the same pass over the
 * corners the gradient of the loss with respect to each point times its weight (age_s, P):
 * out_points (P, 4), columns 0-2 (column 3 zero), the velocity's gradient at the point. */
int64_t flow_grid_backward(const float *points, int64_t n_points, const float *lo,
                           const float *factor, const int64_t *shape, const float *grad_sigma,
                           const float *grad_rgb, const float *rgb, const float *sigma_grad,
                           const float *table, const float *age_s, int64_t n_rows,
                           float *dense, uint8_t *touched, int64_t *out_rows,
                           float *out_values, float *out_points) {
    int64_t rows[8];
    float w[8], frac[3], inside[3], s[8];
    for (int64_t i = 0; i < n_points; i++) {
        row4 g;
        g[0] = grad_sigma[i] * sigma_grad[i];
        for (int c = 0; c < 3; c++) {
            float v = rgb[3 * i + c];
            g[1 + c] = grad_rgb[3 * i + c] * (v * (1.0f - v));
        }
        corners_frac(points + 3 * i, lo, factor, shape, rows, w, frac, inside);
        for (int k = 0; k < 8; k++) {
            float *row = dense + 4 * rows[k];
            store_row(row, load_row(row) + w[k] * g);
            touched[rows[k]] = 1;
            row4 prod = g * load_row(table + 4 * rows[k]);
            s[k] = (prod[0] + prod[1]) + (prod[2] + prod[3]);
        }
        float gx = 0.0f, gy = 0.0f, gz = 0.0f;
        for (int a = 0; a < 2; a++) {
            for (int b = 0; b < 2; b++) {
                float wa_y = a ? frac[1] : 1.0f - frac[1], wb_z = b ? frac[2] : 1.0f - frac[2];
                float wa_x = a ? frac[0] : 1.0f - frac[0], wb_y = b ? frac[1] : 1.0f - frac[1];
                gx += (s[4 + 2 * a + b] - s[2 * a + b]) * (wa_y * wb_z);
                gy += (s[4 * a + 2 + b] - s[4 * a + b]) * (wa_x * wb_z);
                gz += (s[4 * a + 2 * b + 1] - s[4 * a + 2 * b]) * (wa_x * wb_y);
            }
        }
        float a_i = age_s[i];
        out_points[4 * i] = gx * factor[0] * inside[0] * a_i;
        out_points[4 * i + 1] = gy * factor[1] * inside[1] * a_i;
        out_points[4 * i + 2] = gz * factor[2] * inside[2] * a_i;
        out_points[4 * i + 3] = 0.0f;
    }
    int64_t n = 0;
    for (int64_t r = 0; r < n_rows; r++) {
        if (!touched[r]) continue;
        out_rows[n] = r;
        memcpy(out_values + 4 * n, dense + 4 * r, 4 * sizeof(float));
        memset(dense + 4 * r, 0, 4 * sizeof(float));
        touched[r] = 0;
        n++;
    }
    return n;
}

/* The warp of the flow backend: warped (P, 3) = points + age_s (P) * v(points), v the first
 * three columns of the trilinear interpolation of flow (N, 4). */
void flow_warp(const float *flow, const float *points, const float *age_s, int64_t n_points,
               const float *lo, const float *factor, const int64_t *shape, float *warped) {
    int64_t rows[8];
    float w[8];
    for (int64_t i = 0; i < n_points; i++) {
        corners(points + 3 * i, lo, factor, shape, rows, w);
        row4 acc = {0.0f, 0.0f, 0.0f, 0.0f};
        for (int k = 0; k < 8; k++) acc += w[k] * load_row(flow + 4 * rows[k]);
        for (int d = 0; d < 3; d++) warped[3 * i + d] = points[3 * i + d] + age_s[i] * acc[d];
    }
}

/* grad (N, 4) += the gradient of scale * sum over the axes of the squared second
 * differences of the velocity grid flow (N, 4; columns 0-2) of shape (nx, ny, nz) along
 * that axis (FlowField.smoothness: scale = 2 * flow_smooth / entries, per axis). */
void flow_smooth_grad(const float *flow, const int64_t *shape, const float *scale,
                      float *grad) {
    int64_t stride[3] = {shape[1] * shape[2], shape[2], 1};
    for (int axis = 0; axis < 3; axis++) {
        int64_t n = shape[axis], s = stride[axis];
        if (n < 3) continue;
        float c = scale[axis];
        for (int64_t x = 0; x < shape[0]; x++)
            for (int64_t y = 0; y < shape[1]; y++)
                for (int64_t z = 0; z < shape[2]; z++) {
                    int64_t pos = axis == 0 ? x : (axis == 1 ? y : z);
                    if (pos > n - 3) continue;
                    int64_t r = x * stride[0] + y * stride[1] + z;
                    for (int d = 0; d < 3; d++) {
                        float d2 = (flow[4 * (r + 2 * s) + d] - 2.0f * flow[4 * (r + s) + d])
                                   + flow[4 * r + d];
                        d2 *= c;
                        grad[4 * (r + 2 * s) + d] += d2;
                        grad[4 * (r + s) + d] -= 2.0f * d2;
                        grad[4 * r + d] += d2;
                    }
                }
    }
}
