/* The Cortex-M4F calibration image of buckc_tanhf (the float32 build's tanh, buckc_tanhf.h): what one
 * call costs where the forward passes use it -- inlined in a loop, its constants held in registers.
 *
 * PROBE_STEPS steps, each bracketed by buckc_step_begin() / buckc_step_end() like the replay's
 * (cosim/benchmark_harness/cortex_m4.py counts the instructions between them in QEMU's trace), each
 * computing buckc_tanhf of PROBE_BATCH arguments in buckc_tanh_batch(): a step's cycles over
 * PROBE_BATCH are a call's, with the loop's load, store and branch (as a forward pass has them around
 * each tanh). The arguments run over [-4.5, 4.5): x_k = -4.5 + 9 k / (PROBE_STEPS PROBE_BATCH), exact in
 * float. Printed through semihosting:
 *
 *     tanh <k> <8 hex digits>   the bits of buckc_tanhf(x_k)
 *     done <steps>
 */
#include <stdint.h>
#include <string.h>

#include "buckc.h"
#include "semihosting.h"

#define PROBE_BATCH 16
#define PROBE_STEPS 16

__attribute__((noinline)) void buckc_step_begin(void) { __asm volatile("" ::: "memory"); }
__attribute__((noinline)) void buckc_step_end(void) { __asm volatile("" ::: "memory"); }

__attribute__((noinline)) void buckc_tanh_batch(const float *x, float *y, int n);
__attribute__((noinline)) void buckc_tanh_batch(const float *x, float *y, int n)
{
    int i;
    for (i = 0; i < n; ++i)
        y[i] = buckc_tanhf(x[i]);
}

static char *put_text(char *out, const char *text)
{
    while (*text) *out++ = *text++;
    return out;
}

static char *put_decimal(char *out, uint32_t value)
{
    char digits[10];
    int n = 0;
    do {
        digits[n++] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value);
    while (n) *out++ = digits[--n];
    return out;
}

static char *put_hex(char *out, uint32_t value)
{
    int shift;
    for (shift = 28; shift >= 0; shift -= 4) *out++ = "0123456789abcdef"[(value >> shift) & 0xFu];
    return out;
}

int main(void)
{
    static char line[64];
    static float x[PROBE_STEPS][PROBE_BATCH], y[PROBE_STEPS][PROBE_BATCH];
    uint32_t step, i;
    for (step = 0; step < PROBE_STEPS; ++step)
        for (i = 0; i < PROBE_BATCH; ++i)
            x[step][i] = -4.5f + 9.0f * (float)(step * PROBE_BATCH + i) / (float)(PROBE_STEPS * PROBE_BATCH);
    for (step = 0; step < PROBE_STEPS; ++step) {
        buckc_step_begin();
        buckc_tanh_batch(x[step], y[step], PROBE_BATCH);
        buckc_step_end();
    }
    for (step = 0; step < PROBE_STEPS; ++step)
        for (i = 0; i < PROBE_BATCH; ++i) {
            uint32_t bits;
            memcpy(&bits, &y[step][i], sizeof bits);
            *put_text(put_hex(put_text(put_decimal(put_text(line, "tanh "), step * PROBE_BATCH + i), " "), bits),
                      "\n") = '\0';
            buckc_semihosting_write0(line);
        }
    *put_text(put_decimal(put_text(line, "done "), PROBE_STEPS), "\n") = '\0';
    buckc_semihosting_write0(line);
    return 0;
}
