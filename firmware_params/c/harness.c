/* harness.c: host test harness for the C reference against the golden vectors.
 *
 *   harness GOLDEN_DIR [DIFF_CSV]
 *
 * Reads GOLDEN_DIR/manifest.json, and checks every file it lists with the checker registered for
 * the file's name (CHECKERS below): each column within its tolerance class (bit for bit unless
 * the file's "ulp" object in the manifest gives the column an ulp bound). A listed file without
 * a checker is a failure. Prints per file the rows checked, the rows that differ and, per column,
 * how many rows differ and by how much; writes every difference to DIFF_CSV (file, row, column,
 * expected, got, ulp, bound, within/beyond) when given.
 * Exit 0 when every file passes, 1 on any difference beyond its class, 2 on unreadable input.
 *
 * Host code: it may use stdio and large static buffers; the firmware sources (eol_*.c) may not.
 */
#include "eol_fp.h" /* first: the floating-point contract */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "eol_block.h"
#include "eol_comp.h"
#include "eol_est.h" /* H4 */
#include "eol_mech.h" /* revision 1.2 */

/* ---------------------------------------------------- operation counts (cycle model) ---- */
/* Built with -DEOL_COUNT_OPS against firmware sources whose LLVM IR counts every operation into
 * eol_ops[class] (bench/bench_fw_cycles.py): each call is weighed with the cycles per class in
 * EOL_OPS_WEIGHTS and the worst tick per function is printed per file ("CYCLES ..."). */
#ifdef EOL_COUNT_OPS
#define OPS_N 24
uint64_t eol_ops[OPS_N];
static double g_w[OPS_N];
static uint64_t g_snap[OPS_N];
enum { F_EST, F_MECH, F_BG, F_COMP, F_TICK, F_N };
static double g_worst[F_N];
static long g_worst_row[F_N];

static void ops_mark(void)
{
    memcpy(g_snap, eol_ops, sizeof g_snap);
}

static double ops_cost(void)
{
    double c = 0.0;
    int k;
    for (k = 0; k < OPS_N; ++k) {
        c += (double)(eol_ops[k] - g_snap[k]) * g_w[k];
    }
    ops_mark();
    return c;
}

static void ops_worst(int f, double c, long row)
{
    if (c > g_worst[f]) {
        g_worst[f] = c;
        g_worst_row[f] = row;
    }
}

static void ops_weights(void)
{
    const char *w = getenv("EOL_OPS_WEIGHTS");
    int k = 0;
    while (w != NULL && *w != '\0' && k < OPS_N) {
        char *end;
        g_w[k++] = strtod(w, &end);
        w = (*end == ',') ? end + 1 : end;
    }
}

static void ops_report(const char *file)
{
    static const char *names[F_N] = {"est", "mech_tick", "background", "comp", "tick"};
    int f;
    printf("CYCLES %s", file);
    for (f = 0; f < F_N; ++f) {
        printf(" %s=%.0f@%ld", names[f], g_worst[f], g_worst_row[f]);
        g_worst[f] = 0.0;
        g_worst_row[f] = 0;
    }
    printf("\n");
}
#define OPS_MARK() ops_mark()
#define OPS_COST() ops_cost()
#define OPS_WORST(f, c, row) ops_worst((f), (c), (row))
#else
#define OPS_MARK() ((void)0)
#define OPS_COST() 0.0
#define OPS_WORST(f, c, row) ((void)(c), (void)(row))
#endif

/* ---------------------------------------------------------------- CSV reading (shared) ---- */

#define MAX_LINE (1L << 20)
#define MAX_FIELDS 64
#define MAX_IMAGE_BYTES (1L << 17)

typedef struct {
    FILE *fp;
    char path[1024];
    char line[MAX_LINE];
    char header[4096];
    char *cols[MAX_FIELDS];
    int ncols;
    char *f[MAX_FIELDS];
    int nf;
    long row; /* 1 = first data row */
} csv_t;

static int split(char *s, char **out, int max)
{
    int n = 0;
    char *p = s;
    size_t len = strlen(s);
    while (len > 0 && (s[len - 1] == '\n' || s[len - 1] == '\r')) {
        s[--len] = '\0';
    }
    out[n++] = p;
    for (; *p != '\0'; ++p) {
        if (*p == ',') {
            *p = '\0';
            if (n == max) {
                return -1;
            }
            out[n++] = p + 1;
        }
    }
    return n;
}

static int csv_open(csv_t *c, const char *dir, const char *file)
{
    snprintf(c->path, sizeof c->path, "%s/%s", dir, file);
    c->fp = fopen(c->path, "r");
    c->row = 0;
    if (c->fp == NULL || fgets(c->header, sizeof c->header, c->fp) == NULL) {
        fprintf(stderr, "%s: cannot read\n", c->path);
        return -1;
    }
    c->ncols = split(c->header, c->cols, MAX_FIELDS);
    return c->ncols > 0 ? 0 : -1;
}

/* 1: a row was read, 0: end of file, -1: malformed row */
static int csv_next(csv_t *c)
{
    if (fgets(c->line, (int)sizeof c->line, c->fp) == NULL) {
        return 0;
    }
    c->row++;
    c->nf = split(c->line, c->f, MAX_FIELDS);
    if (c->nf != c->ncols) {
        fprintf(stderr, "%s: row %ld has %d fields, the header %d\n", c->path, c->row, c->nf, c->ncols);
        return -1;
    }
    return 1;
}

static void csv_close(csv_t *c)
{
    if (c->fp != NULL) {
        fclose(c->fp);
    }
    c->fp = NULL;
}

/* index of a column, -1 (with a message) when absent */
static int csv_col(const csv_t *c, const char *name)
{
    int i;
    for (i = 0; i < c->ncols; ++i) {
        if (strcmp(c->cols[i], name) == 0) {
            return i;
        }
    }
    fprintf(stderr, "%s: no column %s\n", c->path, name);
    return -1;
}

static uint32_t hex_u32(const char *s)
{
    return (uint32_t)strtoul(s, NULL, 16);
}

static float hex_f32(const char *s)
{
    uint32_t u = hex_u32(s);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

static uint32_t f32_bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

static int hexval(char ch)
{
    if (ch >= '0' && ch <= '9') return ch - '0';
    if (ch >= 'a' && ch <= 'f') return ch - 'a' + 10;
    if (ch >= 'A' && ch <= 'F') return ch - 'A' + 10;
    return -1;
}

/* hex image -> 16-bit word image as the C28x flash holds it (low byte first); returns the byte
 * count or -1. An odd trailing byte is padded with 0xFF (erased) in its word. */
static long image_words(const char *hex, uint16_t *w, long max_bytes)
{
    long len = (long)strlen(hex);
    long nbytes = len / 2;
    long k;
    if (len % 2 != 0 || nbytes > max_bytes) {
        return -1;
    }
    for (k = 0; k < (nbytes + 1) / 2; ++k) {
        w[k] = 0xFFFFu;
    }
    for (k = 0; k < nbytes; ++k) {
        int hi = hexval(hex[2 * k]);
        int lo = hexval(hex[2 * k + 1]);
        uint16_t byte;
        if (hi < 0 || lo < 0) {
            return -1;
        }
        byte = (uint16_t)((hi << 4) | lo);
        if (k % 2 == 0) {
            w[k / 2] = (uint16_t)((w[k / 2] & 0xFF00u) | byte);
        } else {
            w[k / 2] = (uint16_t)((w[k / 2] & 0x00FFu) | (uint16_t)(byte << 8));
        }
    }
    return nbytes;
}

static uint16_t g_words[MAX_IMAGE_BYTES / 2 + 1];

/* Tolerance classes (manifest.json, each file's "ulp" object): a column named there may differ by
 * up to that many units in the last place (a target whose division and square root are estimates
 * plus Newton steps, as the C28x's); every other column is exact. */
#define MAX_COLS 64
#define COL_NAME 48
#define SHOWN 5 /* differences per column shown on stderr */

typedef struct {
    char name[COL_NAME];
    long rows;             /* rows in which this column differs (within its class or not) */
    long beyond;           /* of those, rows beyond its class */
    unsigned long max_ulp; /* largest difference in ulp (floats; integers count 1 per difference) */
    unsigned long bound;   /* its class: 0 exact, else the ulp bound */
} colstat_t;

typedef struct {
    const char *file;
    long rows;        /* rows checked */
    long rows_bad;    /* rows with a difference beyond its column's class */
    long rows_differ; /* rows with any difference */
    long last_bad, last_differ;
    int ncols;
    colstat_t col[MAX_COLS];
    FILE *diff; /* every difference, one CSV line each (NULL: none written) */
} result_t;

static colstat_t *col_stat(result_t *r, const char *what)
{
    int k;
    for (k = 0; k < r->ncols; ++k) {
        if (strcmp(r->col[k].name, what) == 0) return &r->col[k];
    }
    if (r->ncols == MAX_COLS) return &r->col[MAX_COLS - 1]; /* the last slot gathers the rest */
    snprintf(r->col[r->ncols].name, COL_NAME, "%s", what);
    return &r->col[r->ncols++];
}

/* one difference of `ulp` units in column `what` (integers: ulp 1 and hex values as given) */
static void differ(result_t *r, const csv_t *c, const char *what, unsigned long want, unsigned long got,
                   unsigned long ulp)
{
    colstat_t *s = col_stat(r, what);
    int beyond = ulp > s->bound;
    s->rows++;
    if (ulp > s->max_ulp) s->max_ulp = ulp;
    if (r->last_differ != c->row) {
        r->rows_differ++;
        r->last_differ = c->row;
    }
    if (beyond) {
        s->beyond++;
        if (r->last_bad != c->row) {
            r->rows_bad++;
            r->last_bad = c->row;
        }
    }
    if (s->rows <= SHOWN) { /* a glimpse on stderr, the first few per column; every one in the file */
        fprintf(stderr, "%s: row %ld: %s: expected 0x%08lx, got 0x%08lx (%lu ulp, %s)\n", c->path, c->row, what, want,
                got, ulp, beyond ? "beyond its class" : "within its class");
    }
    if (r->diff != NULL) {
        fprintf(r->diff, "%s,%ld,%s,%08lx,%08lx,%lu,%lu,%s\n", r->file, c->row, what, want, got, ulp, s->bound,
                beyond ? "beyond" : "within");
    }
}

/* an integer or bit-pattern column: exact */
static void fail(result_t *r, const csv_t *c, const char *what, unsigned long want, unsigned long got)
{
    differ(r, c, what, want, got, 1ul);
}

/* distance in units in the last place between two binary32 bit patterns (ordered as integers) */
static unsigned long ulp_distance(uint32_t a, uint32_t b)
{
    long long oa = (a & 0x80000000u) ? -(long long)(a & 0x7FFFFFFFu) : (long long)a;
    long long ob = (b & 0x80000000u) ? -(long long)(b & 0x7FFFFFFFu) : (long long)b;
    long long d = oa > ob ? oa - ob : ob - oa;
    return d > 0xFFFFFFFFll ? 0xFFFFFFFFul : (unsigned long)d;
}

/* a float column against its expected bit pattern, within its class */
static void chk_f32(result_t *r, const csv_t *c, const char *what, uint32_t want, float got)
{
    uint32_t g = f32_bits(got);
    if (g != want) differ(r, c, what, want, g, ulp_distance(want, g));
}

/* the file's "ulp" object in its manifest entry (text from its "name" on, to the next entry) */
static void read_classes(result_t *r, const char *entry, const char *entry_end)
{
    const char *p = strstr(entry, "\"ulp\": {");
    const char *end;
    if (p == NULL || (entry_end != NULL && p > entry_end)) return;
    p += strlen("\"ulp\": {");
    end = strchr(p, '}');
    while (p != NULL && end != NULL && p < end) {
        char name[COL_NAME];
        const char *q = strchr(p, '"');
        const char *q2;
        size_t len;
        if (q == NULL || q > end) break;
        q2 = strchr(q + 1, '"');
        if (q2 == NULL || q2 > end) break;
        len = (size_t)(q2 - q - 1);
        if (len >= COL_NAME) len = COL_NAME - 1;
        memcpy(name, q + 1, len);
        name[len] = '\0';
        q = strchr(q2, ':');
        if (q == NULL || q > end) break;
        col_stat(r, name)->bound = strtoul(q + 1, NULL, 10);
        p = strchr(q, ',');
    }
}

static void report(const result_t *r)
{
    int k;
    if (r->rows == 0 || r->rows_bad != 0) {
        printf("%s: FAIL: %ld of %ld rows differ beyond their class\n", r->file, r->rows_bad, r->rows);
    } else if (r->rows_differ != 0) {
        printf("%s: %ld rows ok, %ld of them within their class\n", r->file, r->rows, r->rows_differ);
    } else {
        printf("%s: %ld rows ok\n", r->file, r->rows);
    }
    for (k = 0; k < r->ncols; ++k) {
        const colstat_t *s = &r->col[k];
        if (s->rows == 0) continue;
        if (s->bound != 0u) {
            printf("    %-14s %6ld rows differ, %ld beyond its class (ulp <= %lu); largest %lu ulp\n", s->name, s->rows,
                   s->beyond, s->bound, s->max_ulp);
        } else {
            printf("    %-14s %6ld rows differ, %ld beyond its class (exact); largest %lu ulp\n", s->name, s->rows,
                   s->beyond, s->max_ulp);
        }
    }
}

/* ------------------------------------------------------------- blocks.csv: field values ---- */

static int check_blocks(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    int rc;
    int i_img, i_ser;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_img = csv_col(&c, "image");
    i_ser = csv_col(&c, "serial");
    if (i_img < 0 || i_ser < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        long nbytes = image_words(c.f[i_img], g_words, MAX_IMAGE_BYTES);
        uint16_t n;
        int col;
        uint32_t s;
        if (nbytes < 0) {
            fprintf(stderr, "%s: row %ld: bad image\n", c.path, c.row);
            return -1;
        }
        r->rows++;
        n = EOL_PB_GET_TABLE_LEN(g_words);
        if (eol_block_check(g_words, (uint32_t)nbytes) != EOL_PB_STATUS_VALID) {
            fail(r, &c, "check status", EOL_PB_STATUS_VALID, eol_block_check(g_words, (uint32_t)nbytes));
        }
        if ((uint32_t)nbytes != EOL_PB_BLOCK_BYTES(n)) {
            fail(r, &c, "image size", EOL_PB_BLOCK_BYTES(n), (unsigned long)nbytes);
        }
        if (eol_crc32_words(g_words, EOL_PB_OFF_CRC32(n)) != EOL_PB_GET_CRC32(g_words, n)) {
            fail(r, &c, "crc32 of the image", EOL_PB_GET_CRC32(g_words, n),
                 eol_crc32_words(g_words, EOL_PB_OFF_CRC32(n)));
        }
        {
            /* the estimator configuration the block gives: its fields and flags word */
            eol_est_config_t k;
            int h;
            if (eol_est_config_from_block(g_words, 1, &k) != 0) {
                fail(r, &c, "eol_est_config_from_block", 0, 1);
            } else {
                if (k.flags != EOL_PB_GET_FLAGS(g_words)) fail(r, &c, "config flags", EOL_PB_GET_FLAGS(g_words), k.flags);
                if (k.poles != (int32_t)EOL_PB_GET_POLES(g_words)) fail(r, &c, "config poles", EOL_PB_GET_POLES(g_words), (unsigned long)k.poles);
                if (k.n_enc != (int32_t)EOL_PB_GET_ENCODER_PPR(g_words)) fail(r, &c, "config n_enc", EOL_PB_GET_ENCODER_PPR(g_words), (unsigned long)k.n_enc);
                if (f32_bits(k.tick_hz) != f32_bits(EOL_PB_GET_TICK_HZ(g_words))) fail(r, &c, "config tick_hz", f32_bits(EOL_PB_GET_TICK_HZ(g_words)), f32_bits(k.tick_hz));
                for (h = 0; h < 6; ++h) {
                    if (f32_bits(k.hall_angle[h]) != f32_bits(EOL_PB_GET_HALL_ANGLE(g_words, h))) {
                        fail(r, &c, "config hall_angle", f32_bits(EOL_PB_GET_HALL_ANGLE(g_words, h)), f32_bits(k.hall_angle[h]));
                    }
                }
            }
        }
        for (s = 0u; s < EOL_PB_COUNT_SERIAL; ++s) {
            size_t len = strlen(c.f[i_ser]);
            uint16_t want = (uint16_t)(s < len ? (unsigned char)c.f[i_ser][s] : 0u);
            if (EOL_PB_GET_SERIAL(g_words, s) != want) {
                fail(r, &c, "serial byte", want, EOL_PB_GET_SERIAL(g_words, s));
            }
        }
        for (col = 0; col < c.ncols; ++col) {
            const char *name = c.cols[col];
            const char *v = c.f[col];
            unsigned long want = strtoul(v, NULL, 10);
            unsigned long got;
            if (col == i_img || col == i_ser || strcmp(name, "id") == 0) continue;
#define INT_FIELD(key, expr) else if (strcmp(name, key) == 0) { got = (unsigned long)(expr); if (got != want) fail(r, &c, key, want, got); }
#define F32_FIELD(key, expr) else if (strcmp(name, key) == 0) { chk_f32(r, &c, key, hex_u32(v), expr); }
            if (0) {
            }
            INT_FIELD("sequence", EOL_PB_GET_SEQUENCE(g_words))
            INT_FIELD("flags", EOL_PB_GET_FLAGS(g_words))
            INT_FIELD("calibrated_at", EOL_PB_GET_CALIBRATED_AT(g_words))
            INT_FIELD("poles", EOL_PB_GET_POLES(g_words))
            INT_FIELD("encoder_ppr", EOL_PB_GET_ENCODER_PPR(g_words))
            INT_FIELD("table_len", EOL_PB_GET_TABLE_LEN(g_words))
            INT_FIELD("block_bytes", EOL_PB_GET_BLOCK_BYTES(g_words))
            INT_FIELD("crc32", EOL_PB_GET_CRC32(g_words, n))
            F32_FIELD("tick_hz", EOL_PB_GET_TICK_HZ(g_words))
            F32_FIELD("kt", EOL_PB_GET_KT(g_words))
            F32_FIELD("c6", EOL_PB_GET_C6(g_words))
            F32_FIELD("phase_c6", EOL_PB_GET_PHASE_C6(g_words))
            F32_FIELD("k6", EOL_PB_GET_K6(g_words))
            F32_FIELD("phase_k6", EOL_PB_GET_PHASE_K6(g_words))
            F32_FIELD("lead_s", EOL_PB_GET_LEAD_S(g_words))
            F32_FIELD("iqc_limit", EOL_PB_GET_IQC_LIMIT(g_words))
            else if (strncmp(name, "hall_angle_", 11) == 0) {
                int s_idx = atoi(name + 11);
                want = hex_u32(v);
                got = f32_bits(EOL_PB_GET_HALL_ANGLE(g_words, s_idx - 1));
                if (s_idx < 1 || s_idx > 6 || got != want) fail(r, &c, name, want, got);
            } else {
                fprintf(stderr, "%s: unknown column %s\n", c.path, name);
                return -1;
            }
#undef INT_FIELD
#undef F32_FIELD
        }
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

/* ---------------------------------------------------- block_checks.csv: check routine ---- */

static int check_block_checks(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    int rc;
    int i_img, i_status, i_len;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_img = csv_col(&c, "image");
    i_status = csv_col(&c, "status");
    i_len = csv_col(&c, "image_bytes");
    if (i_img < 0 || i_status < 0 || i_len < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        long nbytes = image_words(c.f[i_img], g_words, MAX_IMAGE_BYTES);
        unsigned long want = strtoul(c.f[i_status], NULL, 10);
        unsigned long got;
        if (nbytes < 0 || nbytes != strtol(c.f[i_len], NULL, 10)) {
            fprintf(stderr, "%s: row %ld: bad image\n", c.path, c.row);
            return -1;
        }
        r->rows++;
        got = eol_block_check(g_words, (uint32_t)nbytes);
        if (got != want) fail(r, &c, "check status", want, got);
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

/* ----------------------------------------------------------- compensator.csv: i_qc ---- */

#define MAX_BLOCKS 16

typedef struct {
    char id[64];
    uint16_t n;
    float lead_s, iqc_limit;
    float table_const[EOL_PB_TABLE_LEN_MAX];
    float table_per_amp[EOL_PB_TABLE_LEN_MAX];
} comp_block_t;

static comp_block_t g_blocks[MAX_BLOCKS];
static int g_nblocks;

/* tables, lead and limit of every block in blocks.csv, read through the header's accessors */
static int load_blocks(const char *dir)
{
    static csv_t c;
    int rc, i_img, i_id;
    g_nblocks = 0;
    if (csv_open(&c, dir, "blocks.csv") != 0) return -1;
    i_img = csv_col(&c, "image");
    i_id = csv_col(&c, "id");
    if (i_img < 0 || i_id < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        comp_block_t *b = &g_blocks[g_nblocks];
        long nbytes = image_words(c.f[i_img], g_words, MAX_IMAGE_BYTES);
        uint16_t j;
        if (nbytes < 0 || g_nblocks == MAX_BLOCKS ||
            eol_block_check(g_words, (uint32_t)nbytes) != EOL_PB_STATUS_VALID) {
            fprintf(stderr, "%s: row %ld: not a valid block\n", c.path, c.row);
            return -1;
        }
        snprintf(b->id, sizeof b->id, "%s", c.f[i_id]);
        b->n = EOL_PB_GET_TABLE_LEN(g_words);
        b->lead_s = EOL_PB_GET_LEAD_S(g_words);
        b->iqc_limit = EOL_PB_GET_IQC_LIMIT(g_words);
        for (j = 0u; j < b->n; ++j) {
            b->table_const[j] = EOL_PB_GET_TABLE_CONST(g_words, b->n, j);
            b->table_per_amp[j] = EOL_PB_GET_TABLE_PER_AMP(g_words, b->n, j);
        }
        g_nblocks++;
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

static int check_compensator(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    int rc, i_id, i_th, i_om, i_iq, i_out;
    if (load_blocks(dir) != 0) return -1;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_id = csv_col(&c, "block_id");
    i_th = csv_col(&c, "theta_hat");
    i_om = csv_col(&c, "omega_hat");
    i_iq = csv_col(&c, "i_qo");
    i_out = csv_col(&c, "i_qc");
    if (i_id < 0 || i_th < 0 || i_om < 0 || i_iq < 0 || i_out < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        const comp_block_t *b = NULL;
        int k;
        float y;
        for (k = 0; k < g_nblocks; ++k) {
            if (strcmp(g_blocks[k].id, c.f[i_id]) == 0) b = &g_blocks[k];
        }
        if (b == NULL) {
            fprintf(stderr, "%s: row %ld: unknown block_id %s\n", c.path, c.row, c.f[i_id]);
            return -1;
        }
        r->rows++;
        y = eol_comp_iqc(hex_f32(c.f[i_th]), hex_f32(c.f[i_om]), hex_f32(c.f[i_iq]), b->table_const,
                         b->table_per_amp, b->n, b->lead_s, b->iqc_limit);
        chk_f32(r, &c, "i_qc", hex_u32(c.f[i_out]), y);
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

/* ==================================================== ESTIMATOR SET (H4) ==== begin ====
 * estimator_configs.csv: each scenario's configuration and the constants eol_est_init derives;
 * estimator_*.csv: eol_est_init with the first row's inputs, then one eol_est_step per row. */

/* the configuration row of scenario `file` from estimator_configs.csv; with `r` also checks the
 * derived constants of every row */
static int est_config(const char *dir, const char *file, eol_est_config_t *cfg, result_t *r)
{
    static csv_t c;
    static eol_est_t e;
    int rc, found = 0, s;
    int i_file = -1, i_poles, i_nenc, i_tick, i_ss, i_flags, i_opts, i_ha[6];
    char name[32];
    if (csv_open(&c, dir, "estimator_configs.csv") != 0) return -1;
    i_file = csv_col(&c, "file");
    i_poles = csv_col(&c, "poles");
    i_nenc = csv_col(&c, "N_enc");
    i_tick = csv_col(&c, "tick_hz");
    i_ss = csv_col(&c, "standstill_ticks");
    i_flags = csv_col(&c, "block_flags");
    i_opts = csv_col(&c, "options");
    if (i_file < 0 || i_poles < 0 || i_nenc < 0 || i_tick < 0 || i_ss < 0 || i_flags < 0 || i_opts < 0) return -1;
    for (s = 0; s < 6; ++s) {
        snprintf(name, sizeof name, "hall_angle_%d", s + 1);
        if ((i_ha[s] = csv_col(&c, name)) < 0) return -1;
    }
    while ((rc = csv_next(&c)) == 1) {
        eol_est_config_t k;
        int col;
        k.poles = (int32_t)strtol(c.f[i_poles], NULL, 10);
        k.n_enc = (int32_t)strtol(c.f[i_nenc], NULL, 10);
        k.tick_hz = hex_f32(c.f[i_tick]);
        for (s = 0; s < 6; ++s) k.hall_angle[s] = hex_f32(c.f[i_ha[s]]);
        k.standstill_ticks = (int32_t)strtol(c.f[i_ss], NULL, 10);
        k.flags = (uint32_t)strtoul(c.f[i_flags], NULL, 10);
        if (file != NULL && strcmp(c.f[i_file], file) == 0) {
            *cfg = k;
            found = 1;
        }
        if (r == NULL) continue;
        r->rows++;
        /* the options the block's flags select, as the Python reference reads them */
        if (eol_est_options(k.flags) != strtoul(c.f[i_opts], NULL, 10)) {
            fail(r, &c, "options", strtoul(c.f[i_opts], NULL, 10), eol_est_options(k.flags));
        }
        if (eol_est_init(&e, &k, 0, 0, 0) != 0) {
            fail(r, &c, "eol_est_init", 0, 1);
            continue;
        }
        for (col = 0; col < c.ncols; ++col) {
            const char *cn = c.cols[col];
            float got;
            if (strcmp(cn, "T") == 0) got = e.T;
            else if (strcmp(cn, "DELTA") == 0) got = e.DELTA;
            else if (strcmp(cn, "QUARTER") == 0) got = e.QUARTER;
            else if (strcmp(cn, "K_OMEGA") == 0) got = e.K_OMEGA;
            else if (strcmp(cn, "K_NDELTA") == 0) got = e.K_NDELTA;
            else if (strncmp(cn, "h_width_", 8) == 0) got = e.h_width[atoi(cn + 8)];
            else if (strncmp(cn, "h_mid_", 6) == 0) got = e.h_mid[atoi(cn + 6)];
            else continue;
            chk_f32(r, &c, cn, hex_u32(c.f[col]), got);
        }
    }
    csv_close(&c);
    if (rc < 0) return -1;
    if (file != NULL && !found) {
        fprintf(stderr, "estimator_configs.csv: no row for %s\n", file);
        return -1;
    }
    return 0;
}

static int check_estimator_configs(const char *dir, const char *file, result_t *r)
{
    eol_est_config_t unused;
    (void)file;
    return est_config(dir, NULL, &unused, r);
}

static int check_estimator(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    static eol_est_t e;
    eol_est_config_t cfg;
    int rc, i_a, i_b, i_h, i_th, i_om, i_te, i_st;
    if (est_config(dir, file, &cfg, NULL) != 0) return -1;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_a = csv_col(&c, "enc_a");
    i_b = csv_col(&c, "enc_b");
    i_h = csv_col(&c, "hall");
    i_th = csv_col(&c, "theta_hat");
    i_om = csv_col(&c, "omega_hat");
    i_te = csv_col(&c, "theta_enc");
    i_st = csv_col(&c, "status");
    if (i_a < 0 || i_b < 0 || i_h < 0 || i_th < 0 || i_om < 0 || i_te < 0 || i_st < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        eol_est_out_t o;
        int32_t a = (int32_t)strtol(c.f[i_a], NULL, 10);
        int32_t b = (int32_t)strtol(c.f[i_b], NULL, 10);
        int32_t h = (int32_t)strtol(c.f[i_h], NULL, 10);
        unsigned long want_st = strtoul(c.f[i_st], NULL, 10);
        if (c.row == 1 && eol_est_init(&e, &cfg, h, a, b) != 0) {
            fprintf(stderr, "%s: configuration refused by eol_est_init\n", c.path);
            return -1;
        }
        r->rows++;
        OPS_MARK();
        eol_est_step(&e, a, b, h, &o);
        OPS_WORST(F_EST, OPS_COST(), c.row);
        chk_f32(r, &c, "theta_hat", hex_u32(c.f[i_th]), o.theta_hat);
        chk_f32(r, &c, "omega_hat", hex_u32(c.f[i_om]), o.omega_hat);
        chk_f32(r, &c, "theta_enc", hex_u32(c.f[i_te]), o.theta_enc);
        if ((unsigned long)o.status != want_st) fail(r, &c, "status", want_st, (unsigned long)o.status);
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}
/* ===================================================== ESTIMATOR SET (H4) ==== end ====== */

/* ============================================ LAYOUT 2 / MECHANICAL SET (rev 1.2) ==== begin ====
 * blocks_v2.csv: valid layout-2 blocks; mech_configs.csv: each scenario's block and constants;
 * mech_*.csv: eol_est_step + eol_mech_step + eol_comp_iqc_mech tick by tick;
 * mech_compensator.csv: eol_mech_sum + eol_comp_iqc_mech over counts, offsets and angles. */

#define MAX_V2_BLOCKS 8
#define V2_WORDS 8192 /* 16 KiB: a layout-2 block of table_len 1024 needs 11 440 bytes */

typedef struct {
    char id[64];
    uint16_t w[V2_WORDS];
} v2_block_t;

static v2_block_t g_v2[MAX_V2_BLOCKS];
static int g_nv2 = -1;

static int load_v2_blocks(const char *dir)
{
    static csv_t c;
    int rc, i_img, i_id;
    if (g_nv2 >= 0) return 0;
    g_nv2 = 0;
    if (csv_open(&c, dir, "blocks_v2.csv") != 0) return -1;
    i_img = csv_col(&c, "image");
    i_id = csv_col(&c, "id");
    if (i_img < 0 || i_id < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        v2_block_t *b = &g_v2[g_nv2];
        long nbytes;
        if (g_nv2 == MAX_V2_BLOCKS || (long)strlen(c.f[i_img]) / 2 > 2L * V2_WORDS) {
            fprintf(stderr, "%s: row %ld: too many or too large blocks\n", c.path, c.row);
            return -1;
        }
        nbytes = image_words(c.f[i_img], b->w, 2L * V2_WORDS);
        if (nbytes < 0 || eol_block_check(b->w, (uint32_t)nbytes) != EOL_PB_STATUS_VALID) {
            fprintf(stderr, "%s: row %ld: not a valid block\n", c.path, c.row);
            return -1;
        }
        snprintf(b->id, sizeof b->id, "%s", c.f[i_id]);
        g_nv2++;
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

static const uint16_t *v2_block(const char *id)
{
    int k;
    for (k = 0; k < g_nv2; ++k) {
        if (strcmp(g_v2[k].id, id) == 0) return g_v2[k].w;
    }
    fprintf(stderr, "no layout-2 block %s in blocks_v2.csv\n", id);
    return NULL;
}

static int check_blocks_v2(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    int rc, col, i_img;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_img = csv_col(&c, "image");
    if (i_img < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        long nbytes = image_words(c.f[i_img], g_words, MAX_IMAGE_BYTES);
        uint16_t n;
        if (nbytes < 0) return -1;
        r->rows++;
        n = EOL_PB_GET_TABLE_LEN(g_words);
        if (eol_block_check(g_words, (uint32_t)nbytes) != EOL_PB_STATUS_VALID) {
            fail(r, &c, "check status", EOL_PB_STATUS_VALID, eol_block_check(g_words, (uint32_t)nbytes));
        }
        if ((uint32_t)nbytes != EOL_PB_V2_BLOCK_BYTES(n)) fail(r, &c, "image size", EOL_PB_V2_BLOCK_BYTES(n), (unsigned long)nbytes);
        if (!eol_mech_enabled(g_words)) fail(r, &c, "eol_mech_enabled", 1, 0);
        for (col = 0; col < c.ncols; ++col) {
            const char *name = c.cols[col];
            const char *v = c.f[col];
            unsigned long want = strtoul(v, NULL, 10);
            unsigned long got;
            if (col == i_img || strcmp(name, "id") == 0) continue;
#define INT_FIELD(key, expr) else if (strcmp(name, key) == 0) { got = (unsigned long)(expr); if (got != want) fail(r, &c, key, want, got); }
#define F32_FIELD(key, expr) else if (strcmp(name, key) == 0) { chk_f32(r, &c, key, hex_u32(v), expr); }
            if (0) {
            }
            INT_FIELD("sequence", EOL_PB_GET_SEQUENCE(g_words))
            INT_FIELD("flags", EOL_PB_GET_FLAGS(g_words))
            INT_FIELD("table_len", n)
            INT_FIELD("block_bytes", EOL_PB_GET_BLOCK_BYTES(g_words))
            INT_FIELD("fp_len", EOL_PB_V2_GET_FP_LEN(g_words, n))
            INT_FIELD("fp_dirs", EOL_PB_V2_GET_FP_DIRS(g_words, n))
            INT_FIELD("crc32", EOL_PB_V2_GET_CRC32(g_words, n))
            F32_FIELD("grid_phase", EOL_PB_V2_GET_GRID_PHASE(g_words, n))
            F32_FIELD("id_min_score", EOL_PB_V2_GET_ID_MIN_SCORE(g_words, n))
            F32_FIELD("id_margin", EOL_PB_V2_GET_ID_MARGIN(g_words, n))
            F32_FIELD("id_frac_tol", EOL_PB_V2_GET_ID_FRAC_TOL(g_words, n))
            else {
                fprintf(stderr, "%s: unknown column %s\n", c.path, name);
                return -1;
            }
#undef INT_FIELD
#undef F32_FIELD
        }
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

/* the scenario's block and standstill bound from mech_configs.csv; with r, checks every row's constants */
static int mech_config(const char *dir, const char *file, const uint16_t **w, int32_t *standstill, result_t *r)
{
    static csv_t c;
    static eol_est_t e;
    static eol_mech_t m;
    int rc, found = 0, i_file, i_blk, i_ss;
    if (load_v2_blocks(dir) != 0) return -1;
    if (csv_open(&c, dir, "mech_configs.csv") != 0) return -1;
    i_file = csv_col(&c, "file");
    i_blk = csv_col(&c, "block_id");
    i_ss = csv_col(&c, "standstill_ticks");
    if (i_file < 0 || i_blk < 0 || i_ss < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        const uint16_t *bw = v2_block(c.f[i_blk]);
        int32_t ss = (int32_t)strtol(c.f[i_ss], NULL, 10);
        eol_est_config_t cfg;
        int col;
        if (bw == NULL) return -1;
        if (file != NULL && strcmp(c.f[i_file], file) == 0) {
            *w = bw;
            *standstill = ss;
            found = 1;
        }
        if (r == NULL) continue;
        r->rows++;
        if (eol_est_config_from_block(bw, ss, &cfg) != 0 || eol_est_init(&e, &cfg, 0, 0, 0) != 0 ||
            eol_mech_init(&m, &e, bw) != 0) {
            fail(r, &c, "init", 0, 1);
            continue;
        }
        for (col = 0; col < c.ncols; ++col) {
            const char *cn = c.cols[col];
            float got;
            if (strcmp(cn, "DELTA") == 0) got = m.DELTA;
            else if (strcmp(cn, "INV_DELTA") == 0) got = m.INV_DELTA;
            else if (strcmp(cn, "KM") == 0) got = m.KM;
            else if (strcmp(cn, "EF_0") == 0) got = m.EF[0];
            else if (strcmp(cn, "EF_1") == 0) got = m.EF[1];
            else continue;
            chk_f32(r, &c, cn, hex_u32(c.f[col]), got);
        }
    }
    csv_close(&c);
    if (rc < 0) return -1;
    if (file != NULL && !found) {
        fprintf(stderr, "mech_configs.csv: no row for %s\n", file);
        return -1;
    }
    return 0;
}

static int check_mech_configs(const char *dir, const char *file, result_t *r)
{
    const uint16_t *w;
    int32_t ss;
    (void)file;
    return mech_config(dir, NULL, &w, &ss, r);
}

static int check_mech(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    static eol_est_t e;
    static eol_mech_t m;
    const uint16_t *w = NULL;
    int32_t ss = 0;
    eol_est_config_t cfg;
    int rc, i_a, i_b, i_h, i_iq, i_st, i_le, i_ac, i_r, i_ev, i_sc, i_mg, i_out;
    uint16_t n;
    if (mech_config(dir, file, &w, &ss, NULL) != 0) return -1;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_a = csv_col(&c, "enc_a");
    i_b = csv_col(&c, "enc_b");
    i_h = csv_col(&c, "hall");
    i_iq = csv_col(&c, "i_qo");
    i_st = csv_col(&c, "status");
    i_le = csv_col(&c, "learn");
    i_ac = csv_col(&c, "active");
    i_r = csv_col(&c, "r");
    i_ev = csv_col(&c, "events");
    i_sc = csv_col(&c, "score");
    i_mg = csv_col(&c, "margin");
    i_out = csv_col(&c, "i_qc");
    if (i_a < 0 || i_b < 0 || i_h < 0 || i_iq < 0 || i_st < 0 || i_le < 0 || i_ac < 0 || i_r < 0 || i_ev < 0 ||
        i_sc < 0 || i_mg < 0 || i_out < 0) return -1;
    n = EOL_PB_GET_TABLE_LEN(w);
    if (eol_est_config_from_block(w, ss, &cfg) != 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        eol_est_out_t o;
        eol_mech_out_t mo;
        int32_t a = (int32_t)strtol(c.f[i_a], NULL, 10);
        int32_t b = (int32_t)strtol(c.f[i_b], NULL, 10);
        int32_t h = (int32_t)strtol(c.f[i_h], NULL, 10);
        float iq = hex_f32(c.f[i_iq]);
        float sm, y = 0.0f;
        double c_est, c_mech, c_comp = 0.0;
        if (c.row == 1 && (eol_est_init(&e, &cfg, h, a, b) != 0 || eol_mech_init(&m, &e, w) != 0)) {
            fprintf(stderr, "%s: configuration refused\n", c.path);
            return -1;
        }
        r->rows++;
        OPS_MARK();
        eol_est_step(&e, a, b, h, &o);
        c_est = OPS_COST();
        eol_mech_step(&m, &e, &o, &mo);
        c_mech = OPS_COST();
#ifdef EOL_EVAL_IN_TICK
        /* the structure before the background: every slice of an evaluation inside this tick */
        while ((m.busy >= 1) && (m.busy <= m.n_slices)) {
            eol_mech_background(&m, &e);
        }
        eol_mech_background(&m, &e); /* a mark check */
        c_mech += OPS_COST();
#else
        eol_mech_background(&m, &e); /* the golden schedule: one background slice per tick */
#endif
        OPS_WORST(F_BG, OPS_COST(), c.row);
        if (EOL_PB_GET_FLAGS(w) & EOL_PB_FLAG_COMP_ENABLE) {
            static float tc[EOL_PB_TABLE_LEN_MAX], tp[EOL_PB_TABLE_LEN_MAX];
            uint16_t j;
            for (j = 0u; j < n; ++j) {
                tc[j] = EOL_PB_GET_TABLE_CONST(w, n, j);
                tp[j] = EOL_PB_GET_TABLE_PER_AMP(w, n, j);
            }
            OPS_MARK();
            sm = eol_mech_sum(&m, mo.r, e.q, o.theta_hat, o.omega_hat, iq);
            y = eol_comp_iqc_mech(o.theta_hat, o.omega_hat, iq, tc, tp, n, EOL_PB_GET_LEAD_S(w),
                                  EOL_PB_GET_IQC_LIMIT(w), mo.active, sm);
            c_comp = OPS_COST();
        }
        OPS_WORST(F_EST, c_est, c.row);
        OPS_WORST(F_MECH, c_mech, c.row);
        OPS_WORST(F_COMP, c_comp, c.row);
        OPS_WORST(F_TICK, c_est + c_mech + c_comp, c.row);
        if ((unsigned long)o.status != strtoul(c.f[i_st], NULL, 10)) fail(r, &c, "status", strtoul(c.f[i_st], NULL, 10), (unsigned long)o.status);
        if ((unsigned long)o.learn != strtoul(c.f[i_le], NULL, 10)) fail(r, &c, "learn", strtoul(c.f[i_le], NULL, 10), (unsigned long)o.learn);
        if ((unsigned long)mo.active != strtoul(c.f[i_ac], NULL, 10)) fail(r, &c, "active", strtoul(c.f[i_ac], NULL, 10), (unsigned long)mo.active);
        if ((unsigned long)mo.r != strtoul(c.f[i_r], NULL, 10)) fail(r, &c, "r", strtoul(c.f[i_r], NULL, 10), (unsigned long)mo.r);
        if ((unsigned long)mo.events != strtoul(c.f[i_ev], NULL, 10)) fail(r, &c, "events", strtoul(c.f[i_ev], NULL, 10), (unsigned long)mo.events);
        chk_f32(r, &c, "score", hex_u32(c.f[i_sc]), mo.score);
        chk_f32(r, &c, "margin", hex_u32(c.f[i_mg]), mo.margin);
        chk_f32(r, &c, "i_qc", hex_u32(c.f[i_out]), y);
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}

static int check_mech_compensator(const char *dir, const char *file, result_t *r)
{
    static csv_t c;
    static eol_est_t e;
    static eol_mech_t m;
    static float tc[EOL_PB_TABLE_LEN_MAX], tp[EOL_PB_TABLE_LEN_MAX];
    static char current[64] = "";
    int rc, i_id, i_q, i_r, i_th, i_om, i_iq, i_out;
    if (load_v2_blocks(dir) != 0) return -1;
    if (csv_open(&c, dir, file) != 0) return -1;
    i_id = csv_col(&c, "block_id");
    i_q = csv_col(&c, "q");
    i_r = csv_col(&c, "r");
    i_th = csv_col(&c, "theta_hat");
    i_om = csv_col(&c, "omega_hat");
    i_iq = csv_col(&c, "i_qo");
    i_out = csv_col(&c, "i_qc");
    if (i_id < 0 || i_q < 0 || i_r < 0 || i_th < 0 || i_om < 0 || i_iq < 0 || i_out < 0) return -1;
    while ((rc = csv_next(&c)) == 1) {
        const uint16_t *w = v2_block(c.f[i_id]);
        uint16_t n;
        float th, om, iq, sm, y;
        if (w == NULL) return -1;
        n = EOL_PB_GET_TABLE_LEN(w);
        if (strcmp(current, c.f[i_id]) != 0) {
            eol_est_config_t cfg;
            uint16_t j;
            if (eol_est_config_from_block(w, 20000, &cfg) != 0 || eol_est_init(&e, &cfg, 0, 0, 0) != 0 ||
                eol_mech_init(&m, &e, w) != 0) return -1;
            for (j = 0u; j < n; ++j) {
                tc[j] = EOL_PB_GET_TABLE_CONST(w, n, j);
                tp[j] = EOL_PB_GET_TABLE_PER_AMP(w, n, j);
            }
            snprintf(current, sizeof current, "%s", c.f[i_id]);
        }
        r->rows++;
        th = hex_f32(c.f[i_th]);
        om = hex_f32(c.f[i_om]);
        iq = hex_f32(c.f[i_iq]);
        sm = eol_mech_sum(&m, (int32_t)strtol(c.f[i_r], NULL, 10), (int32_t)strtol(c.f[i_q], NULL, 10), th, om, iq);
        y = eol_comp_iqc_mech(th, om, iq, tc, tp, n, EOL_PB_GET_LEAD_S(w), EOL_PB_GET_IQC_LIMIT(w), 1, sm);
        chk_f32(r, &c, "i_qc", hex_u32(c.f[i_out]), y);
    }
    csv_close(&c);
    return rc < 0 ? -1 : 0;
}
/* ============================================= LAYOUT 2 / MECHANICAL SET (rev 1.2) ==== end ==== */

/* ------------------------------------------------------------------------ dispatch ---- */

typedef int (*checker_fn)(const char *dir, const char *file, result_t *r);

typedef struct {
    const char *prefix; /* the file name starts with this (exact name for the fixed sets) */
    checker_fn fn;
} checker_t;

static const checker_t CHECKERS[] = {
    {"blocks.csv", check_blocks},
    {"block_checks.csv", check_block_checks},
    {"compensator.csv", check_compensator},
    /* ESTIMATOR SET (H4): the configs file first, its prefix is longer */
    {"estimator_configs.csv", check_estimator_configs},
    {"estimator_", check_estimator},
    /* layout 2 (revision 1.2) */
    {"blocks_v2.csv", check_blocks_v2},
    {"block_checks_v2.csv", check_block_checks},
    {"mech_configs.csv", check_mech_configs},
    {"mech_compensator.csv", check_mech_compensator},
    {"mech_", check_mech},
};

static char g_manifest[1L << 16];

int main(int argc, char **argv)
{
    const char *dir;
    char path[1024];
    FILE *fp;
    size_t len;
    const char *p;
    const char *key = "\"name\": \"";
    int files = 0, bad = 0;
    FILE *diff = NULL;
    static result_t r;

    if (argc != 2 && argc != 3) {
        fprintf(stderr, "usage: %s GOLDEN_DIR [DIFF_CSV]\n", argv[0]);
        return 2;
    }
    dir = argv[1];
#ifdef EOL_COUNT_OPS
    ops_weights();
#endif
    if (argc == 3) {
        diff = fopen(argv[2], "w");
        if (diff == NULL) {
            fprintf(stderr, "%s: cannot write\n", argv[2]);
            return 2;
        }
        fprintf(diff, "file,row,column,expected,got,ulp,bound,class\n");
    }
    snprintf(path, sizeof path, "%s/manifest.json", dir);
    fp = fopen(path, "r");
    if (fp == NULL) {
        fprintf(stderr, "%s: cannot open\n", path);
        return 2;
    }
    len = fread(g_manifest, 1, sizeof g_manifest - 1, fp);
    fclose(fp);
    g_manifest[len] = '\0';

    /* every "name": "FILE" entry of the manifest's file list */
    for (p = strstr(g_manifest, key); p != NULL; p = strstr(p, key)) {
        char file[256];
        const char *end;
        size_t k, nlen;
        const checker_t *chk = NULL;
        int rc;
        p += strlen(key);
        end = strchr(p, '"');
        if (end == NULL || (size_t)(end - p) >= sizeof file) {
            fprintf(stderr, "%s: malformed file name\n", path);
            return 2;
        }
        nlen = (size_t)(end - p);
        memcpy(file, p, nlen);
        file[nlen] = '\0';
        memset(&r, 0, sizeof r);
        r.file = file;
        r.diff = diff;
        r.last_bad = r.last_differ = -1;
        read_classes(&r, end, strstr(end, key));
        for (k = 0; k < sizeof CHECKERS / sizeof CHECKERS[0]; ++k) {
            if (strncmp(file, CHECKERS[k].prefix, strlen(CHECKERS[k].prefix)) == 0) {
                chk = &CHECKERS[k];
                break;
            }
        }
        files++;
        if (chk == NULL) {
            fprintf(stderr, "%s: FAIL: no checker for this file\n", file);
            bad++;
            continue;
        }
        rc = chk->fn(dir, file, &r);
        if (rc != 0) {
            fprintf(stderr, "%s: ERROR: cannot check\n", file);
            if (diff != NULL) fclose(diff);
            return 2;
        }
        report(&r);
#ifdef EOL_COUNT_OPS
        ops_report(file);
#endif
        if (r.rows == 0 || r.rows_bad != 0) bad++;
    }
    if (files == 0) {
        fprintf(stderr, "%s: lists no files\n", path);
        return 2;
    }
    if (diff != NULL) fclose(diff);
    printf("%s: %d files, %d failed\n", bad ? "FAIL" : "PASS", files, bad);
    return bad ? 1 : 0;
}
