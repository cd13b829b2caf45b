/* Ray marching with empty-space skipping on the CPU (bounded fields: uniform steps, no space warp).
 *
 * Emits exactly the samples core/render/raymarch.py's segment path emits: step k of a ray covers
 * [t_near + k*step, min(t_near + (k+1)*step, t_far)], is evaluated at t_start + frac*(t_end - t_start)
 * (frac = 0.5, or a hash of (seed, ray, k) when jittered) and is kept when the occupancy cell holding its
 * evaluation point is occupied. Walking a ray one step at a time would test hundreds of steps; instead an
 * empty cell is crossed in one jump (instant-ngp's advance to the next voxel), to the first step that may
 * leave it. Arithmetic follows the PyTorch path's float32 operation order (built with -ffp-contract=off).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* Plain comparisons: without -ffast-math fminf and fmaxf are library calls. Inputs here are never NaN. */
#define MINF(a, b) ((a) < (b) ? (a) : (b))
#define MAXF(a, b) ((a) > (b) ? (a) : (b))

static inline float hash_uniform(uint64_t seed, int64_t ray, int64_t k) {
    uint64_t z = seed ^ ((uint64_t)ray * 0x9E3779B97F4A7C15ull) ^ ((uint64_t)k * 0xC2B2AE3D27D4EB4Full);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull; /* splitmix64 finaliser */
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return (float)(z >> 40) * (1.0f / 16777216.0f); /* 24 bits: uniform in [0, 1) */
}

#define MAX_CASCADES 16

typedef struct {
    const uint8_t *occ, *coarse; /* coarse: blocks of `factor`^3 cells, set when any cell inside is occupied */
    int32_t res, cascades, factor;
    float bound, outer;
    float ext[MAX_CASCADES], scale[MAX_CASCADES], size[MAX_CASCADES]; /* half-size, cells per unit, cell size */
} Grid;

static void grid_init(Grid *g, const uint8_t *occ, const uint8_t *coarse, int32_t factor, int32_t res,
                      int32_t cascades, float bound) {
    g->occ = occ;
    g->coarse = factor > 1 ? coarse : 0;
    g->factor = factor > 1 ? factor : 1;
    g->res = res;
    g->cascades = cascades;
    g->bound = bound;
    for (int32_t c = 0; c < cascades; c++) {
        const double e = (double)bound * ldexp(1.0, c);
        g->ext[c] = (float)e;
        g->scale[c] = (float)((double)res / (2.0 * e)); /* as PyTorch: the double ratio, rounded once */
        g->size[c] = (float)(2.0 * e / res);
    }
    g->outer = g->ext[cascades - 1];
}

/* Cascade and cell of point x, as OccupancyGrid.cascade_of / _cell_index; -1 when outside every cascade. */
static inline int64_t cell_of(const Grid *g, const float *x, int32_t *casc, int32_t *ijk) {
    if (isnan(x[0] + x[1] + x[2])) return -1;
    const float m = MAXF(fabsf(x[0]), MAXF(fabsf(x[1]), fabsf(x[2])));
    if (!(m <= g->outer)) return -1;
    int32_t c = 0;
    if (g->cascades > 1) {
        const float l = ceilf(log2f(MAXF(m, 1e-30f) / g->bound));
        c = l < 0.0f ? 0 : (l > (float)(g->cascades - 1) ? g->cascades - 1 : (int32_t)l);
    }
    const float ef = g->ext[c], sc = g->scale[c];
    const int32_t r = g->res;
    int64_t flat = 0;
    for (int a = 0; a < 3; a++) {
        int32_t i = (int32_t)((x[a] + ef) * sc);
        i = i < 0 ? 0 : (i > r - 1 ? r - 1 : i);
        ijk[a] = i;
        flat = flat * r + i;
    }
    *casc = c;
    return (int64_t)c * r * r * r + flat;
}

/* Distance at which the ray (origin o, inverse direction inv) leaves box ijk of cascade c, a box being
 * `span`^3 cells; for c > 0 no farther than where it enters the inner cascade's cube, whose finer cells
 * take over there. */
static inline float box_exit(const Grid *g, const float *o, const float *inv, int32_t c, const int32_t *ijk,
                             int32_t span) {
    const float e = g->ext[c], size = g->size[c] * (float)span;
    float t_exit = INFINITY;
    for (int a = 0; a < 3; a++) {
        if (isinf(inv[a])) continue;
        const float face = (float)(ijk[a] + (inv[a] > 0.0f)) * size - e;
        t_exit = MINF(t_exit, (face - o[a]) * inv[a]);
    }
    if (c > 0) {
        const float ei = g->ext[c - 1];
        float t0 = -INFINITY, t1 = INFINITY;
        for (int a = 0; a < 3; a++) {
            if (isinf(inv[a])) {
                if (fabsf(o[a]) > ei) return t_exit;
                continue;
            }
            const float ta = (-ei - o[a]) * inv[a], tb = (ei - o[a]) * inv[a];
            t0 = MAXF(t0, MINF(ta, tb));
            t1 = MINF(t1, MAXF(ta, tb));
        }
        if (t0 <= t1 && t1 > 0.0f) t_exit = MINF(t_exit, t0);
    }
    return t_exit;
}

/* For the rays ids[0..n_ids), starting at step next_k[ray], emit up to `take` occupied samples each and
 * advance next_k past the last emitted (or to n_steps when the ray ran out). Outputs are packed, sorted by
 * ray then distance; returns their number (at most n_ids * take, the buffers' size). */
int64_t mr_march(const float *o, const float *d, const float *t_near, const float *t_far, const int64_t *n_steps,
                 float step, const int64_t *ids, int64_t n_ids, int64_t *next_k, int32_t take,
                 const uint8_t *occ, const uint8_t *coarse, int32_t factor, int32_t res, int32_t cascades,
                 float bound, int32_t jitter, uint64_t seed,
                 int64_t *out_ray, float *out_ts, float *out_te, float *out_t, float *out_x, int32_t *count,
                 int32_t threads) {
    if (cascades < 1 || cascades > MAX_CASCADES) return -1;
    Grid g;
    grid_init(&g, occ, coarse, factor, res, cascades, bound);
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads)
    for (int64_t j = 0; j < n_ids; j++) {
        const int64_t r = ids[j];
        const float *ro = o + 3 * r, *rd = d + 3 * r;
        float inv[3];
        for (int a = 0; a < 3; a++) inv[a] = rd[a] != 0.0f ? 1.0f / rd[a] : INFINITY;
        const float tn = t_near[r], tf = t_far[r];
        const int64_t n = n_steps[r];
        int64_t k = next_k[r];
        int32_t got = 0;
        const int64_t base = j * (int64_t)take;
        while (k < n && got < take) {
            const float ts = tn + (float)k * step;
            const float te = MINF(ts + step, tf);
            const float frac = jitter ? hash_uniform(seed, r, k) : 0.5f;
            const float t = ts + frac * (te - ts);
            float x[3];
            for (int a = 0; a < 3; a++) x[a] = ro[a] + t * rd[a];
            int32_t c, ijk[3];
            const int64_t cell = cell_of(&g, x, &c, ijk);
            if (cell >= 0 && occ[cell]) {
                const int64_t s = base + got++;
                out_ray[s] = r;
                out_ts[s] = ts;
                out_te[s] = te;
                out_t[s] = t;
                memcpy(out_x + 3 * s, x, sizeof x);
                k++;
                continue;
            }
            int64_t kn = k + 1;
            if (cell >= 0) { /* steps ending before the box's exit (less a margin for rounding) stay inside it */
                int32_t span = 1;
                if (g.coarse) { /* an empty block of cells is crossed in one jump */
                    const int32_t f = g.factor, rc = g.res / f;
                    int32_t b[3] = {ijk[0] / f, ijk[1] / f, ijk[2] / f};
                    if (!g.coarse[(((int64_t)c * rc + b[0]) * rc + b[1]) * rc + b[2]]) {
                        span = f;
                        memcpy(ijk, b, sizeof b);
                    }
                }
                const float t_exit = box_exit(&g, ro, inv, c, ijk, span);
                const float jump = floorf((t_exit - 1e-2f * step - tn) / step); /* first step ending past it */
                if (jump > (float)kn && jump < (float)n) kn = (int64_t)jump;
                else if (jump >= (float)n) kn = n;
            }
            k = kn;
        }
        next_k[r] = k;
        count[j] = got;
    }
    int64_t total = 0; /* compact the per-ray slots in order (destinations never pass their sources) */
    for (int64_t j = 0; j < n_ids; j++) {
        const int64_t src = j * (int64_t)take, cnt = count[j];
        if (cnt && src != total) {
            memmove(out_ray + total, out_ray + src, cnt * sizeof *out_ray);
            memmove(out_ts + total, out_ts + src, cnt * sizeof *out_ts);
            memmove(out_te + total, out_te + src, cnt * sizeof *out_te);
            memmove(out_t + total, out_t + src, cnt * sizeof *out_t);
            memmove(out_x + 3 * total, out_x + 3 * src, 3 * cnt * sizeof *out_x);
        }
        total += cnt;
    }
    return total;
}
