/* ARM semihosting (the "Semihosting for AArch32 and AArch64" specification): the image's only way
 * out of the emulator -- text to the host's console and the exit status. On M-profile a call is
 * BKPT 0xAB with the operation in r0 and its argument in r1. */
#ifndef BUCKC_SEMIHOSTING_H
#define BUCKC_SEMIHOSTING_H

#include <stddef.h>

void buckc_semihosting_write0(const char *text);            /* SYS_WRITE0: a NUL-terminated string */
__attribute__((noreturn)) void buckc_semihosting_exit(int ok); /* SYS_EXIT: ApplicationExit, or a run-time error */

#endif
