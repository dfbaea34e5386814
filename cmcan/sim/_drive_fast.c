/* The simulator's time integration (cmcan/sim/drive.py, integrate) in C: the same loop, step by
 * step, for the same numbers to the bit. cmcan/sim/drive.py calls it through the ctypes handle of
 * cmcan/io/native.py (one library, _native.so); without the library, or with CMCAN_NATIVE=0, the
 * Python loop runs, and it is the reference: every expression here is transcribed from it in the
 * same order of operations, and the library is compiled without contraction into fused
 * multiply-adds (-ffp-contract=off) and without -ffast-math.
 *
 * Python's operators and math functions are C's plus their errors: a float division by zero,
 * float ** float overflowing, math.sqrt of a negative number, math.log10 of one at or below zero
 * raise where C goes on with an infinity or a NaN. Each such point is checked, and where Python
 * would raise the loop stops and reports how far it came: the caller then runs the Python loop,
 * which raises the same exception (and if a check was too careful, computes the same numbers).
 * The exponents of ** come from the caller, so no compiler turns pow(x, 2.0) into x * x (which
 * libm's pow need not equal to the last bit).
 *
 * Plain C with no Python API: the caller owns every buffer. */
#include <errno.h>
#include <math.h>
#include <stdint.h>

/* The constants of the loop, in the order of cmcan/sim/drive.py's _hoisted (k[...]) */
enum {
    K_A_W,
    K_B_W,
    K_RHO15,
    K_DRHO,
    K_K_LINE,
    K_D_M_NOM,
    K_LAM_P,
    K_LAM_M,
    K_TURB,
    K_COMP_P,
    K_LAM_X,
    K_LIN_X,
    K_ORF_X,
    K_FILL_X,
    K_COMP_M,
    K_RELIEF_DP,
    K_RELIEF_GAIN,
    K_INERTIA,
    K_FRICTION,
    K_VISCOUS,
    K_FADE,
    K_HEAT_CAP,
    K_COOLER,
    K_HM_LOSS,
    K_KELVIN,
    K_CC,
    K_MIN_DP_FOR_SQRT,
    K_TEN, /* 10.0: the base of 10.0 ** x */
    K_TWO, /* 2.0: the exponent of cosh(x) ** 2 */
    K_COUNT
};

int32_t cmcan_drive_constants(void) { return K_COUNT; }

/* a / b, Python's: ZeroDivisionError at b == 0 */
static inline double py_div(double a, double b, int *bad) {
    if (b == 0.0) *bad = 1;
    return a / b;
}

/* iv ** iw, Python's (CPython's float_pow) for a finite base above zero, the only bases here:
 * its special cases first, then C's pow with OverflowError where errno says so (an underflow to
 * zero is no error) */
static inline double py_pow(double iv, double iw, int *bad) {
    if (!(isfinite(iv) && iv > 0.0)) { /* not a base of this loop: let Python decide */
        *bad = 1;
        return 0.0;
    }
    if (iw == 0) return 1.0;
    if (isnan(iw)) return iv == 1.0 ? 1.0 : iw;
    if (isinf(iw)) {
        if (iv == 1.0) return 1.0;
        if ((iw > 0.0) == (iv > 1.0)) return fabs(iw);
        return 0.0;
    }
    if (iv == 1.0) return 1.0;
    errno = 0;
    double ix = pow(iv, iw);
    if (errno == 0) {
        if (ix == HUGE_VAL || ix == -HUGE_VAL) errno = ERANGE;
    } else if (errno == ERANGE && ix == 0.0) {
        errno = 0;
    }
    if (errno != 0) *bad = 1;
    return ix;
}

/* math.sqrt, math.tanh, math.cosh (CPython's math_1): ValueError or OverflowError where libm
 * answers NaN to a number or infinity to a finite number */
static inline double py_math_1(double x, double r, int *bad) {
    if ((isnan(r) && !isnan(x)) || (isinf(r) && isfinite(x))) *bad = 1;
    return r;
}

/* math.log10 (CPython's m_log10 under math_1) */
static inline double py_log10(double x, int *bad) {
    if (isfinite(x)) {
        if (x > 0.0) return log10(x);
        *bad = 1;
        return x == 0.0 ? -HUGE_VAL : NAN;
    }
    if (isnan(x)) return x;
    if (x > 0.0) return x;
    *bad = 1;
    return NAN;
}

/* n steps of dt_s from state (dp, w, temp), left there at the end; the raw outputs of each step
 * (dp in Pa, speed in rad/s, temperature in C, extra leakage in m3/s). Returns the number of steps
 * done: n, or the step at which Python would raise (state and outputs are then not to be used). */
int64_t cmcan_drive_integrate(int64_t n, const double *k, double dt_s, const double *n_p_l,
                              const double *v_p_l, const double *tl_l, const double *tp_l,
                              const double *ta_l, const double *gp_l, const double *gm_l,
                              const double *hb_l, const double *mf_l, double *state, double *out_dp,
                              double *out_w, double *out_t, double *out_x) {
    const double a_w = k[K_A_W], b_w = k[K_B_W];
    const double rho15 = k[K_RHO15], drho = k[K_DRHO];
    const double k_line = k[K_K_LINE];
    const double d_m_nom = k[K_D_M_NOM];
    const double lam_p = k[K_LAM_P], lam_m = k[K_LAM_M];
    const double turb = k[K_TURB];
    const double comp_p = k[K_COMP_P];
    const double lam_x = k[K_LAM_X], lin_x = k[K_LIN_X], orf_x = k[K_ORF_X], fill_x = k[K_FILL_X];
    const double comp_m = k[K_COMP_M];
    const double relief_dp = k[K_RELIEF_DP], relief_gain = k[K_RELIEF_GAIN];
    const double inertia = k[K_INERTIA], friction = k[K_FRICTION], viscous = k[K_VISCOUS];
    const double fade = k[K_FADE];
    const double heat_cap = k[K_HEAT_CAP], cooler = k[K_COOLER], hm_loss = k[K_HM_LOSS];
    const double KELVIN = k[K_KELVIN], CC = k[K_CC], MIN_DP_FOR_SQRT = k[K_MIN_DP_FOR_SQRT];
    const double ten = k[K_TEN], two = k[K_TWO];

    double dp = state[0], w = state[1], temp = state[2];
    int bad = 0;
    int64_t i;
    for (i = 0; i < n; i++) {
        double t_pres = tp_l[i];
        if (t_pres == t_pres) temp = t_pres; /* not NaN: prescribed temperature */
        double nu = py_pow(ten, py_pow(ten, a_w - b_w * py_log10(temp + KELVIN, &bad), &bad), &bad) - 0.7;
        double rho = rho15 * (1.0 - drho * (temp - 15.0));
        double mu = nu * 1e-6 * rho;
        double n_p = n_p_l[i];
        double q_geo = n_p / 60.0 * v_p_l[i] * CC;
        double q_fill = fill_x * n_p * n_p;
        double d_m = d_m_nom * mf_l[i];

        /* Leakage conductance (linear part) and sqrt-law part at the current pressure. */
        double g_lin = py_div(lam_p + lam_m + lam_x + gp_l[i] + gm_l[i], mu, &bad) + lin_x + comp_p * q_geo;
        double adp = dp >= 0.0 ? dp : -dp;
        double x = py_div(2.0 * adp, rho, &bad);
        double root = py_math_1(x, sqrt(x), &bad);
        double h_b = hb_l[i] + orf_x;
        double h_sq = turb * root + h_b * py_math_1(adp, sqrt(adp), &bad);
        double q_sq = dp >= 0.0 ? h_sq : -h_sq;
        double adp_c = adp > MIN_DP_FOR_SQRT ? adp : MIN_DP_FOR_SQRT;
        x = py_div(2.0, rho * adp_c, &bad);
        double dq_sq = 0.5 * (turb * py_math_1(x, sqrt(x), &bad) +
                              py_div(h_b, py_math_1(adp_c, sqrt(adp_c), &bad), &bad));
        double q_motor = w * d_m * (1.0 + comp_m * dp);
        double q_base = g_lin * dp + q_sq;
        double fd_base = -k_line * (g_lin + dq_sq + w * d_m * comp_m);
        double fw = -k_line * d_m * (1.0 + comp_m * dp);

        /* Load torque opposes motion and fades to zero at standstill. */
        double z = py_div(w, fade, &bad);
        double th = py_math_1(z, tanh(z), &bad);
        double t_load = tl_l[i] * th;
        double t_fric = friction * th + viscous * w;
        double g0 = py_div(d_m * dp - t_load - t_fric, inertia, &bad);
        double gd = py_div(d_m, inertia, &bad);
        double sech2 = fabs(z) < 50.0 ? py_div(1.0, py_pow(py_math_1(z, cosh(z), &bad), two, &bad), &bad) : 0.0;
        double gw = py_div(-(py_div((tl_l[i] + friction) * sech2, fade, &bad) + viscous), inertia, &bad);

        /* Linearly implicit step: (I - dt J) dx = dt f, solved again with the relief valve open
         * where the step would cross its setting. */
        int relief_open = dp > relief_dp;
        double q_leak = 0.0, dp_new = 0.0, w_new = 0.0;
        for (int it = 0; it < 2; it++) {
            double fd;
            if (relief_open) {
                q_leak = q_base + relief_gain * (dp - relief_dp);
                fd = fd_base - k_line * relief_gain;
            } else {
                q_leak = q_base;
                fd = fd_base;
            }
            double f0 = k_line * (q_geo - q_fill - q_leak - q_motor);
            double a11 = 1.0 - dt_s * fd;
            double a12 = -dt_s * fw;
            double a21 = -dt_s * gd;
            double a22 = 1.0 - dt_s * gw;
            double det = a11 * a22 - a12 * a21;
            double r1 = dt_s * f0;
            double r2 = dt_s * g0;
            dp_new = dp + py_div(r1 * a22 - a12 * r2, det, &bad);
            w_new = w + py_div(a11 * r2 - a21 * r1, det, &bad);
            if (relief_open || dp_new <= relief_dp) break;
            relief_open = 1;
        }
        dp = dp_new;
        w = w_new;

        double extra = py_div(gp_l[i] + gm_l[i], mu, &bad) * dp + hb_l[i] * py_math_1(fabs(dp), sqrt(fabs(dp)), &bad);
        if (t_pres != t_pres) {
            double p_loss = q_leak * dp + hm_loss * q_geo * fabs(dp) + t_fric * w;
            temp += py_div(dt_s * (p_loss - cooler * (temp - ta_l[i])), heat_cap, &bad);
        }
        if (bad) break;

        out_dp[i] = dp;
        out_w[i] = w;
        out_t[i] = temp;
        out_x[i] = extra;
    }
    state[0] = dp;
    state[1] = w;
    state[2] = temp;
    return i;
}
