/* Replays a recorded kernel plan and frames through frame_kernel.c, with no Python: how the kernel is
 * checked on another architecture (tools/kernel_aarch64.sh builds this for aarch64 and runs it under
 * qemu-user; tools/kernel_aarch64.py writes the input and compares the output).
 *
 *   harness IN OUT
 *
 * IN: "OKV1", then entries until the end: u16 name length, the name, u8 kind ('f' float32, 'd' float64,
 * 'i' int32, 'q' int64, 'b' uint8), u64 count, the values (little-endian, as the machine). Scalars are
 * float64 entries of one value. The plan's entries carry the names the CPython module reads
 * (kernel/module.c); "state_*" entries the kernel's state after the baseline (levels, the gain's
 * reference time); "frames" (uint8, n_frames * frame_bytes) and "times" (int64 per frame) the frames.
 * OUT: per frame, int32 contacts, then contacts * OK_FIELDS float64.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "frame_kernel.h"

typedef struct {
    char name[64];
    char kind;
    uint64_t count;
    void *data;
} entry;

static entry entries[256];
static int n_entries;

static int read_file(const char *path) {
    FILE *f = fopen(path, "rb");
    if (!f) return -1;
    char magic[4];
    if (fread(magic, 1, 4, f) != 4 || memcmp(magic, "OKV1", 4) != 0) return -1;
    for (;;) {
        uint16_t len;
        if (fread(&len, 2, 1, f) != 1) break;
        entry *e = &entries[n_entries];
        if (n_entries >= 256 || len >= sizeof e->name || fread(e->name, 1, len, f) != len) return -1;
        e->name[len] = 0;
        if (fread(&e->kind, 1, 1, f) != 1 || fread(&e->count, 8, 1, f) != 1) return -1;
        size_t size = e->kind == 'f' || e->kind == 'i' ? 4 : e->kind == 'b' ? 1 : 8;
        e->data = malloc(e->count * size + 64);
        if (!e->data || fread(e->data, size, e->count, f) != e->count) return -1;
        n_entries++;
    }
    fclose(f);
    return 0;
}

static entry *find(const char *name) {
    for (int i = 0; i < n_entries; i++)
        if (!strcmp(entries[i].name, name)) return &entries[i];
    return NULL;
}

static void *arr(const char *name) {
    entry *e = find(name);
    return e ? e->data : NULL;
}

static uint64_t count(const char *name) {
    entry *e = find(name);
    return e ? e->count : 0;
}

static double num(const char *name) {
    entry *e = find(name);
    if (!e) {
        fprintf(stderr, "harness: missing %s\n", name);
        exit(2);
    }
    return ((double *)e->data)[0];
}

static void axis(ok_axis *a, const char *prefix) {
    char km[64], kt[64];
    snprintf(km, sizeof km, "%s_km", prefix);
    snprintf(kt, sizeof kt, "%s_kt", prefix);
    a->km = arr(km);
    a->kt = arr(kt);
    a->k = (int32_t)count(km);
}

static void radial(ok_radial_map *m, const char *prefix) {
    char name[64];
    snprintf(name, sizeof name, "%s_feature", prefix);
    m->feature = (int32_t)num(name);
    snprintf(name, sizeof name, "%s_power", prefix);
    m->power = (int32_t)num(name);
    snprintf(name, sizeof name, "%s_radial", prefix);
    m->radial = num(name);
    snprintf(name, sizeof name, "%s_radius_mm", prefix);
    m->radius_mm = num(name);
    axis(&m->curve, prefix);
}

int main(int argc, char **argv) {
    if (argc != 3 || read_file(argv[1]) < 0) {
        fprintf(stderr, "usage: harness IN OUT (IN as tools/kernel_aarch64.py writes it)\n");
        return 2;
    }
    ok_plan p;
    memset(&p, 0, sizeof p);
    p.n_fibers = (int32_t)num("n_fibers");
    p.rgb = (int32_t)num("rgb");
    p.n = (int32_t)num("n");
    p.relative = (int32_t)num("relative");
    p.compensate_gain = (int32_t)num("compensate_gain");
    p.track_baseline = (int32_t)num("track_baseline");
    p.bright_from_common = (int32_t)num("bright_from_common");
    p.max_contacts = (int32_t)num("max_contacts");
    p.frame_pixels = (int64_t)num("frame_pixels");
    p.black_level = (float)num("black_level");
    p.gain_rate_per_ns = num("gain_rate_per_ns");
    p.tau_ns = num("tau_ns");
    p.holdoff_ns = num("holdoff_ns");
    p.bright_hold_ns = num("bright_hold_ns");
    p.x0_mm = num("x0_mm");
    p.y0_mm = num("y0_mm");
    p.step_mm = num("step_mm");
    p.cell_area_mm2 = num("cell_area_mm2");
    p.min_area_mm2 = num("min_area_mm2");
    p.min_cells = num("min_cells");
    p.peak_fraction = num("peak_fraction");
    p.shape_fraction = num("shape_fraction");
    p.split_fraction = num("split_fraction");
    p.pixel_index = arr("pixel_index");
    p.pixel_start = arr("pixel_start");
    p.inv_count = arr("inv_count");
    p.rgb_weights = arr("rgb_weights"); /* NULL: BT.601 */
    p.dead = arr("dead");
    p.n_dead = (int32_t)count("dead");
    p.live = arr("live");
    p.n_live = (int32_t)count("live");
    p.means = arr("means");
    p.signal = arr("signal");
    p.surface = arr("surface");
    p.baseline = arr("baseline");
    p.level = arr("level");
    p.inv_level = arr("inv_level");
    p.band = arr("band"); /* NULL when the plan has none */
    p.support_nbr = arr("support_nbr");
    p.rest = arr("rest");
    p.contacts = arr("contacts");
    p.dense = arr("dense");
    p.tri_cols = arr("tri_cols");
    if (p.tri_cols) {
        p.n_tri = (int32_t)num("n_tri");
        p.width = (int32_t)num("width");
        p.n_value_terms = (int32_t)num("n_value_terms");
        p.value_rows = arr("value_rows");
        p.n_value_rows = (int32_t)count("value_rows");
        p.value_op = arr("value_op");
        p.grad_op = arr("grad_op");
        p.tri_cells = arr("tri_cells");
        p.tri_count = arr("tri_count");
        p.tri_weights = arr("tri_weights");
        p.value_w = arr("value_w");
        p.grad_w = arr("grad_w");
        if (find("gs_fibers")) {
            p.gs_fibers = arr("gs_fibers");
            p.gs_diag = arr("gs_diag");
            p.gs_col_last = arr("gs_col_last");
            p.gs_col_ptr = arr("gs_col_ptr");
            p.gs_col_env = arr("gs_col_env");
            p.gs_nbr_ptr = arr("gs_nbr_ptr");
            p.gs_nbr = arr("gs_nbr");
            p.gs_coef = arr("gs_coef");
        }
    }
    ok_models *m = &p.models;
    if (find("cmap_n")) {
        m->cmap_n = (int32_t)num("cmap_n");
        m->cmap_x0 = num("cmap_x0");
        m->cmap_y0 = num("cmap_y0");
        m->cmap_step = num("cmap_step");
        m->cmap_ex = arr("cmap_ex");
        m->cmap_ey = arr("cmap_ey");
    }
    if (find("width_major_km")) {
        m->width = 1;
        axis(&m->major, "width_major");
        axis(&m->minor, "width_minor");
        m->radial_major = num("width_radial_major");
        m->radial_minor = num("width_radial_minor");
        m->width_radius_mm = num("width_radius_mm");
    }
    if (find("depth_km")) {
        m->depth = 1;
        radial(&m->depth_map, "depth");
        if (find("force_km")) {
            m->force = 1;
            radial(&m->force_map, "force");
        }
    }
    if (find("shape_d")) {
        m->shape_d = (int32_t)num("shape_d");
        m->shape_k = (int32_t)num("shape_k");
        m->shape_c = (int32_t)num("shape_c");
        m->shape_sel = arr("shape_sel");
        m->shape_rule = arr("shape_rule");
        m->shape_mean = arr("shape_mean");
        m->shape_std = arr("shape_std");
        m->shape_cap = num("shape_cap");
        m->shape_q4_floor = num("shape_q4_floor");
        m->shape_q4_max = num("shape_q4_max");
        m->shape_proj1 = arr("shape_proj1");
        m->shape_const = arr("shape_const");
        m->shape_map1 = arr("shape_map1");
    }
    static ok_kernel k;
    char err[200];
    if (ok_kernel_init(&k, &p, err, sizeof err) < 0) {
        fprintf(stderr, "harness: %s\n", err);
        return 1;
    }
    ok_set_levels(&k, (float)num("state_trunc"), (float)num("state_off"), (float)num("state_on"),
                  num("state_gain_delta"), num("state_gain_tolerance"), num("state_gain_significant"));
    ok_reset_gain(&k, (int64_t)num("state_reference_ns"));
    k.correct = (int32_t)num("state_correct");
    const uint8_t *frames = arr("frames");
    const int64_t *times = arr("times");
    uint64_t n_frames = count("times"), frame_bytes = (uint64_t)num("frame_bytes");
    int64_t last = (int64_t)num("state_last_ns");
    FILE *out = fopen(argv[2], "wb");
    if (!frames || !times || !out) {
        fprintf(stderr, "harness: no frames, or cannot write %s\n", argv[2]);
        return 1;
    }
    for (uint64_t f = 0; f < n_frames; f++) {
        int32_t n = ok_frame(&k, frames + f * frame_bytes, times[f], times[f] - last, 0);
        last = times[f];
        fwrite(&n, 4, 1, out);
        fwrite(p.contacts, sizeof(double), (size_t)n * OK_FIELDS, out);
    }
    fclose(out);
    ok_kernel_free(&k);
    return 0;
}
