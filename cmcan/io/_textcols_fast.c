/* Rows of text from columns, in C, for the replay's writers (the timeline CSV and the emitted
 * candump log): cmcan/io/native.py calls it with ctypes, which releases the GIL, so the writer thread
 * formats on the second core while the engine works.
 *
 * Each column is a kind with its arrays, preceded by a literal prefix; the row ends with a literal.
 * Fixed-point numbers are written to the byte as Python's f"{x:.{d}f}": the exact binary value
 * rounded half to even. As cmcan/io/textcols.py does with arrays, the fraction is scaled by 10^d in
 * floating point, and a value within a few ulps of a rounding boundary (and anything at or beyond
 * 2^52) is written by snprintf, which rounds the exact value (glibc), as Python does. NaN is an
 * empty cell: a value that is not there (a tick not evaluated has no prediction). */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

enum { K_FIXED = 0, K_INT = 1, K_NAME = 2, K_HEX_ID = 3, K_HEX_DATA = 4 };

static const double POW10D[10] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9};
static const int64_t POW10I[10] = {1, 10, 100, 1000, 10000, 100000, 1000000, 10000000, 100000000, 1000000000};
static const char HEX[] = "0123456789ABCDEF";

static char *put_uint(char *o, uint64_t v, int min_digits) {
    char tmp[24];
    int n = 0;
    do {
        tmp[n++] = (char)('0' + v % 10);
        v /= 10;
    } while (v);
    while (n < min_digits) tmp[n++] = '0';
    while (n) *o++ = tmp[--n];
    return o;
}

/* NULL when the text would not fit before end */
static char *put_fixed(char *o, char *end, double x, int d) {
    if (isnan(x)) return o; /* a value that is not there: an empty cell */
    double ax = fabs(x);
    if (ax < 4503599627370496.0) { /* 2^52 */
        double whole = floor(ax);
        double scaled = (ax - whole) * POW10D[d];
        double m = scaled > 1.0 ? scaled : 1.0;
        double ulp = nextafter(m, INFINITY) - m;
        if (!(fabs(scaled - floor(scaled) - 0.5) <= 4.0 * ulp)) {
            if (end - o < 20 + 1 + d) return NULL;
            int64_t ip = (int64_t)whole;
            int64_t fp = (int64_t)rint(scaled);
            if (d) {
                if (fp >= POW10I[d]) {
                    ip += 1;
                    fp -= POW10I[d];
                }
            } else {
                ip += fp;
            }
            if (signbit(x)) *o++ = '-';
            o = put_uint(o, (uint64_t)ip, 1);
            if (d) {
                *o++ = '.';
                o = put_uint(o, (uint64_t)fp, d);
            }
            return o;
        }
    }
    int k = snprintf(o, (size_t)(end - o), "%.*f", d, x); /* exact: ties, huge values, infinities */
    if (k < 0 || k >= end - o) return NULL;
    return o + k;
}

/* Returns the bytes written to out, or -1 when they would exceed cap (the caller formats otherwise).
 * Per column c: kind[c], arg[c] (decimals of K_FIXED), a[c] and b[c] its arrays:
 *   K_FIXED    a: double[n]
 *   K_INT      a: int64[n]
 *   K_NAME     a: int64[n] index into the names, b: int32[] offsets (names k at text[off[k]:off[k+1]]),
 *              names text in t[c]
 *   K_HEX_ID   a: uint32[n], b: uint8[n] extended (8 digits, else 3)
 *   K_HEX_DATA a: uint8[n*8], b: int16[n] length (0..8 bytes) */
int64_t cmcan_format_rows(int64_t n, int32_t ncols, const int32_t *kind, const int32_t *arg, const void *const *a,
                          const void *const *b, const char *const *t, const char *const *prefix,
                          const int32_t *prefix_len, const char *row_end, int32_t row_end_len, char *out,
                          int64_t cap) {
    char *o = out, *end = out + cap;
    for (int64_t i = 0; i < n; i++) {
        for (int32_t c = 0; c < ncols; c++) {
            if (end - o < prefix_len[c]) return -1;
            memcpy(o, prefix[c], (size_t)prefix_len[c]);
            o += prefix_len[c];
            switch (kind[c]) {
            case K_FIXED:
                o = put_fixed(o, end, ((const double *)a[c])[i], arg[c]);
                if (!o) return -1;
                break;
            case K_INT: {
                if (end - o < 21) return -1;
                int64_t v = ((const int64_t *)a[c])[i];
                if (v < 0) {
                    *o++ = '-';
                    o = put_uint(o, (uint64_t)0 - (uint64_t)v, 1);
                } else {
                    o = put_uint(o, (uint64_t)v, 1);
                }
                break;
            }
            case K_NAME: {
                int64_t k = ((const int64_t *)a[c])[i];
                const int32_t *off = (const int32_t *)b[c];
                int32_t len = off[k + 1] - off[k];
                if (end - o < len) return -1;
                memcpy(o, t[c] + off[k], (size_t)len);
                o += len;
                break;
            }
            case K_HEX_ID: {
                uint32_t v = ((const uint32_t *)a[c])[i];
                int w = ((const uint8_t *)b[c])[i] ? 8 : 3;
                if (end - o < w) return -1;
                for (int k = w - 1; k >= 0; k--) {
                    o[k] = HEX[v & 0xF];
                    v >>= 4;
                }
                o += w;
                break;
            }
            case K_HEX_DATA: {
                const uint8_t *d = (const uint8_t *)a[c] + i * 8;
                int len = ((const int16_t *)b[c])[i];
                if (len < 0 || len > 8 || end - o < 2 * len) return -1;
                for (int k = 0; k < len; k++) {
                    *o++ = HEX[d[k] >> 4];
                    *o++ = HEX[d[k] & 0xF];
                }
                break;
            }
            default:
                return -1;
            }
        }
        if (end - o < row_end_len) return -1;
        memcpy(o, row_end, (size_t)row_end_len);
        o += row_end_len;
    }
    return o - out;
}
