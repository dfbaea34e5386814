/* candump -l lines of the common shape parsed in C, for the columnar replay's reader
 * (cmcan/io/candump_native.py loads this with ctypes, which releases the GIL for the call: the next
 * chunk is parsed on the second core while the engine works on this one).
 *
 * The common shape, and nothing else:
 *     (DIGITS.DIGITS) CHANNEL ID#HEX\n
 * with at most 19 digits in the stamp (value below 2^53), a channel of 1..31 printable ASCII
 * characters, an identifier of 3 hex digits (at most 0x7FF) or 8 (at most 0x1FFFFFFF), and 0..8
 * data bytes as hex pairs. Any other line (blank, a remote, error or CAN FD frame, an exponent,
 * trailing tokens, '\r\n', an odd digit) is marked for cmcan.io.candump.parse_candump_line, which
 * defines the semantics; tests check both give the same frames.
 *
 * Plain C with no Python API: the caller owns every buffer. */
#include <stdint.h>
#include <string.h>

#define NAME_MAX_LEN 31

static const double POW10[20] = {1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,  1e8,  1e9,
                                 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19};

static inline int hexval(uint8_t c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}

int64_t cmcan_count_lines(const uint8_t *text, int64_t len) {
    int64_t n = 0;
    const uint8_t *p = text, *end = text + len;
    while (p < end) {
        const uint8_t *q = memchr(p, '\n', (size_t)(end - p));
        if (!q) break;
        n++;
        p = q + 1;
    }
    return n;
}

/* One line [p, e) (e at its '\n'); 1 when parsed into row i, 0 when it is for the line reader. */
static int parse_line(const uint8_t *p, const uint8_t *e, int64_t i, double *t, int16_t *chan,
                      uint32_t *cid, uint8_t *ext, int16_t *dlc, uint8_t *data, uint8_t *names,
                      int32_t *name_len, int32_t max_names, int32_t *n_names, int32_t *last_name) {
    if (p >= e || *p != '(') return 0;
    p++;
    uint64_t num = 0;
    int n_int = 0, n_frac = 0;
    while (p < e && *p >= '0' && *p <= '9') {
        if (++n_int > 19) return 0;
        num = num * 10 + (uint64_t)(*p++ - '0');
    }
    if (n_int < 1 || p >= e || *p != '.') return 0;
    p++;
    while (p < e && *p >= '0' && *p <= '9') {
        if (n_int + ++n_frac > 19) return 0;
        num = num * 10 + (uint64_t)(*p++ - '0');
    }
    if (n_frac < 1 || num >= (UINT64_C(1) << 53)) return 0;
    if (e - p < 2 || p[0] != ')' || p[1] != ' ') return 0;
    p += 2;
    /* the channel */
    const uint8_t *c0 = p;
    while (p < e && *p > ' ' && *p < 0x7F) p++;
    int32_t clen = (int32_t)(p - c0);
    if (clen < 1 || clen > NAME_MAX_LEN || p >= e || *p != ' ') return 0;
    p++;
    int32_t code = -1;
    if (*last_name >= 0 && name_len[*last_name] == clen &&
        memcmp(names + (int64_t)*last_name * (NAME_MAX_LEN + 1), c0, (size_t)clen) == 0) {
        code = *last_name;
    } else {
        for (int32_t k = 0; k < *n_names; k++) {
            if (name_len[k] == clen && memcmp(names + (int64_t)k * (NAME_MAX_LEN + 1), c0, (size_t)clen) == 0) {
                code = k;
                break;
            }
        }
        if (code < 0 && *n_names >= max_names) return 0;
    }
    /* the identifier */
    uint32_t id = 0;
    int n_id = 0;
    while (p < e && *p != '#') {
        int v = hexval(*p++);
        if (v < 0 || ++n_id > 8) return 0;
        id = (id << 4) | (uint32_t)v;
    }
    if (p >= e) return 0;
    p++; /* '#' */
    if (n_id == 3) {
        if (id > 0x7FF) return 0;
    } else if (n_id == 8) {
        if (id > 0x1FFFFFFF) return 0;
    } else {
        return 0;
    }
    /* the payload: hex pairs to the end of the line (a remote 'R' or CAN FD '#' is not a hex digit) */
    int64_t nhex = e - p;
    if (nhex > 16 || nhex % 2) return 0;
    uint8_t *d = data + i * 8;
    memset(d, 0, 8);
    for (int64_t k = 0; k < nhex / 2; k++) {
        int hi = hexval(p[2 * k]), lo = hexval(p[2 * k + 1]);
        if (hi < 0 || lo < 0) return 0;
        d[k] = (uint8_t)((hi << 4) | lo);
    }
    if (code < 0) { /* a new name, entered once the line is known good */
        code = (*n_names)++;
        memcpy(names + (int64_t)code * (NAME_MAX_LEN + 1), c0, (size_t)clen);
        name_len[code] = clen;
    }
    t[i] = (double)num / POW10[n_frac]; /* both exact: the correctly rounded decimal, as float() */
    chan[i] = (int16_t)code;
    *last_name = code;
    cid[i] = id;
    ext[i] = n_id == 8;
    dlc[i] = (int16_t)(nhex / 2);
    return 1;
}

/* Parse the lines of text[0:len) (complete lines, each ending in '\n'; at most n_rows of them).
 * Row i of the outputs is line i; fast[i] says whether it was parsed here. Channel names go to
 * names (max_names slots of 32 bytes) with their lengths in name_len, chan[i] indexing them; the
 * table may hold names on entry (*n_names of them) and is added to. Returns the lines seen. */
int64_t cmcan_parse_candump(const uint8_t *text, int64_t len, int64_t n_rows, double *t, int16_t *chan,
                            uint32_t *cid, uint8_t *ext, int16_t *dlc, uint8_t *data, uint8_t *fast,
                            uint8_t *names, int32_t *name_len, int32_t max_names, int32_t *n_names) {
    const uint8_t *p = text, *end = text + len;
    int64_t i = 0;
    int32_t last_name = -1;
    while (p < end && i < n_rows) {
        const uint8_t *e = memchr(p, '\n', (size_t)(end - p));
        if (!e) break;
        fast[i] = (uint8_t)parse_line(p, e, i, t, chan, cid, ext, dlc, data, names, name_len, max_names,
                                      n_names, &last_name);
        if (!fast[i]) {
            t[i] = 0.0;
            chan[i] = -1;
            cid[i] = 0;
            ext[i] = 0;
            dlc[i] = 0;
            memset(data + i * 8, 0, 8);
        }
        i++;
        p = e + 1;
    }
    return i;
}
