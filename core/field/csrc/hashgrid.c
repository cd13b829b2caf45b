/* Multi-resolution hash encoding (instant-ngp) on the CPU: forward and table gradient.
 *
 * Computes exactly what core/field/hashgrid_fast.py:corner_rows_weights + encode_vectorized compute, in one
 * pass per point with no (N, L, 8) intermediates. Built on first use by core/field/hashgrid_native.py and
 * called through ctypes (which releases the GIL). The backward runs one level per thread: levels own
 * disjoint table rows, so no atomics are needed.
 */
#include <math.h>
#include <stdint.h>

#define P1 2654435761u
#define P2 805459861u
#define MAX_F 16

static inline void unit_coords(const float *x, float bound, float *u) {
    const float inv = 2.0f * bound;
    for (int a = 0; a < 3; a++) {
        float v = (x[a] + bound) / inv;
        if (isnan(v)) v = 0.0f;
        u[a] = v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v);
    }
}

static inline void cell_frac(const float *u, int32_t r, uint32_t *c, float *f) {
    const float rf = (float)r;
    for (int a = 0; a < 3; a++) {
        float p = u[a] * rf;
        int32_t ci = (int32_t)floorf(p);
        if (ci > r - 1) ci = r - 1;
        c[a] = (uint32_t)ci;
        f[a] = p - (float)ci;
    }
}

static inline int64_t corner_row(const uint32_t *c, int corner, int32_t r, int32_t dense, uint32_t mask,
                                 int64_t offset) {
    const uint32_t vx = c[0] + (corner & 1), vy = c[1] + ((corner >> 1) & 1), vz = c[2] + ((corner >> 2) & 1);
    uint32_t row;
    if (dense) {
        const uint32_t s = (uint32_t)r + 1u;
        row = vx + vy * s + vz * s * s;
    } else {
        row = (vx ^ (vy * P1) ^ (vz * P2)) & mask;
    }
    return offset + (int64_t)row;
}

static inline float corner_weight(const float *f, int corner) {
    const float wx = (corner & 1) ? f[0] : 1.0f - f[0];
    const float wy = ((corner >> 1) & 1) ? f[1] : 1.0f - f[1];
    const float wz = ((corner >> 2) & 1) ? f[2] : 1.0f - f[2];
    return wx * wy * wz;
}

int hg_max_features(void) { return MAX_F; }

/* One point's encoding; `feats` is a compile-time constant where the caller passes one (the common 2), so the
 * feature loops unroll and the accumulators stay in registers. The sums keep the generic order (bit-identical). */
static inline __attribute__((always_inline)) void forward_point(
        const float *x, const float *table, const int32_t feats, int32_t levels, const int32_t *res,
        const int32_t *dense, const int64_t *offsets, uint32_t mask, float bound, float *o) {
    float u[3];
    unit_coords(x, bound, u);
    for (int32_t l = 0; l < levels; l++) {
        uint32_t c[3];
        float f[3], acc[MAX_F];
        cell_frac(u, res[l], c, f);
        for (int32_t k = 0; k < feats; k++) acc[k] = 0.0f;
        for (int corner = 0; corner < 8; corner++) {
            const float w = corner_weight(f, corner);
            const float *t = table + corner_row(c, corner, res[l], dense[l], mask, offsets[l]) * feats;
            for (int32_t k = 0; k < feats; k++) acc[k] += w * t[k];
        }
        for (int32_t k = 0; k < feats; k++) o[l * feats + k] = acc[k];
    }
}

void hg_forward(const float *x, int64_t n, const float *table, int32_t feats, int32_t levels, const int32_t *res,
                const int32_t *dense, const int64_t *offsets, uint32_t mask, float bound, float *out,
                int32_t threads) {
    const int64_t stride = (int64_t)levels * feats;
    if (feats == 2) {
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t i = 0; i < n; i++)
            forward_point(x + 3 * i, table, 2, levels, res, dense, offsets, mask, bound, out + i * stride);
    } else {
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t i = 0; i < n; i++)
            forward_point(x + 3 * i, table, feats, levels, res, dense, offsets, mask, bound, out + i * stride);
    }
}

/* One level's table gradient from all points (one thread owns the level's rows); `feats` as in forward_point. */
static inline __attribute__((always_inline)) void backward_level(
        const float *x, int64_t n, const float *grad_out, const int32_t feats, int32_t levels, int32_t l,
        const int32_t *res, const int32_t *dense, const int64_t *offsets, uint32_t mask, float bound,
        float *grad_table) {
    const int64_t stride = (int64_t)levels * feats;
    for (int64_t i = 0; i < n; i++) {
        const float *g = grad_out + i * stride + l * feats;
        int any = 0;
        for (int32_t k = 0; k < feats; k++) any |= (g[k] != 0.0f);
        if (!any) continue;
        float u[3], f[3];
        uint32_t c[3];
        unit_coords(x + 3 * i, bound, u);
        cell_frac(u, res[l], c, f);
        for (int corner = 0; corner < 8; corner++) {
            const float w = corner_weight(f, corner);
            float *t = grad_table + corner_row(c, corner, res[l], dense[l], mask, offsets[l]) * feats;
            for (int32_t k = 0; k < feats; k++) t[k] += w * g[k];
        }
    }
}

void hg_backward(const float *x, int64_t n, const float *grad_out, int32_t feats, int32_t levels,
                 const int32_t *res, const int32_t *dense, const int64_t *offsets, uint32_t mask, float bound,
                 float *grad_table, int32_t threads) {
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
    for (int32_t l = levels - 1; l >= 0; l--) {  /* finest (largest) levels first balances the threads */
        if (feats == 2)
            backward_level(x, n, grad_out, 2, levels, l, res, dense, offsets, mask, bound, grad_table);
        else
            backward_level(x, n, grad_out, feats, levels, l, res, dense, offsets, mask, bound, grad_table);
    }
}
