/* Semihosting calls of the Cortex-M4F test image (semihosting.h). */
#include "semihosting.h"

#define SYS_WRITE0 0x04
#define SYS_EXIT 0x18
#define ADP_STOPPED_APPLICATION_EXIT 0x20026   /* QEMU exits with status 0 */
#define ADP_STOPPED_RUN_TIME_ERROR 0x20023     /* QEMU exits with status 1 */

static int call(int operation, const void *argument)
{
    register int r0 __asm("r0") = operation;
    register const void *r1 __asm("r1") = argument;
    __asm volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void buckc_semihosting_write0(const char *text)
{
    call(SYS_WRITE0, text);
}

void buckc_semihosting_exit(int ok)
{
    call(SYS_EXIT, (const void *)(ok ? ADP_STOPPED_APPLICATION_EXIT : ADP_STOPPED_RUN_TIME_ERROR));
    for (;;) {
    }
}
