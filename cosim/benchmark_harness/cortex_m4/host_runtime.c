/* What startup.c and semihosting.c give the replay image on the Cortex-M4F, for the host's build of the
 * same image (cosim/benchmark_harness/cortex_m4.py: host_replay): the console is stdout, and no stack is
 * measured (the stack the steps use is a property of the target's code, measured there). */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

#include "semihosting.h"

uintptr_t buckc_stack_low_water(void);
uintptr_t buckc_stack_low_water(void)
{
    return 0;
}

void buckc_semihosting_write0(const char *text)
{
    fputs(text, stdout);
}

void buckc_semihosting_exit(int ok)
{
    fflush(stdout);
    exit(ok ? 0 : 1);
}
