/* Start-up code of the Cortex-M4F test image: the vector table, the reset handler (copy .data,
 * zero .bss, enable the FPU, paint the stack for the depth measurement, call main), fault
 * handlers that end the run through semihosting. No vendor SDK: the addresses are the ARMv7-M
 * architecture's (System Control Block), the same on every Cortex-M4. */
#include <stdint.h>

#include "semihosting.h"

extern uint32_t __data_start, __data_end, __data_load, __bss_start, __bss_end, __stack_limit, __stack_top;
int main(void);

#define SCB_CPACR (*(volatile uint32_t *)0xE000ED88u) /* Coprocessor Access Control (ARMv7-M ARM B3.2.20) */

/* Every word of the stack below the reset handler's frame holds this before main runs. */
#define STACK_PAINT 0xC5AC5AC5u

void buckc_reset_handler(void);
void buckc_fault_handler(void);

__attribute__((noreturn)) void buckc_reset_handler(void)
{
    uint32_t *src = &__data_load, *dst = &__data_start;
    while (dst < &__data_end) *dst++ = *src++;
    for (dst = &__bss_start; dst < &__bss_end; ++dst) *dst = 0u;
    SCB_CPACR |= 0xFu << 20; /* CP10 and CP11 full access: the single-precision FPU */
    __asm volatile("dsb\n\tisb" ::: "memory");
    {
        uint32_t *sp;
        __asm volatile("mov %0, sp" : "=r"(sp));
        for (dst = &__stack_limit; dst < sp - 16; ++dst) *dst = STACK_PAINT;
    }
    buckc_semihosting_exit(main() == 0);
}

/* The lowest address of the stack written since the reset (the paint ends there). */
uintptr_t buckc_stack_low_water(void);
uintptr_t buckc_stack_low_water(void)
{
    const uint32_t *p = &__stack_limit;
    while (p < &__stack_top && *p == STACK_PAINT) ++p;
    return (uintptr_t)p;
}

__attribute__((noreturn)) void buckc_fault_handler(void)
{
    buckc_semihosting_write0("fault: the controller image took a processor fault (HardFault/MemManage/BusFault/UsageFault)\n");
    buckc_semihosting_exit(0);
}

/* ARMv7-M vector table: initial SP, then the exception handlers (no interrupt is enabled). Words,
 * not function pointers: ISO C has no conversion between object and function pointers. */
#define HANDLER(f) ((uintptr_t)(f))
__attribute__((section(".vectors"), used)) static const uintptr_t vectors[16] = {
    (uintptr_t)&__stack_top,           /* 0: initial main stack pointer */
    HANDLER(buckc_reset_handler),      /* 1: reset */
    HANDLER(buckc_fault_handler),      /* 2: NMI */
    HANDLER(buckc_fault_handler),      /* 3: HardFault */
    HANDLER(buckc_fault_handler),      /* 4: MemManage */
    HANDLER(buckc_fault_handler),      /* 5: BusFault */
    HANDLER(buckc_fault_handler),      /* 6: UsageFault */
    0, 0, 0, 0,                        /* 7-10: reserved */
    HANDLER(buckc_fault_handler),      /* 11: SVCall */
    HANDLER(buckc_fault_handler),      /* 12: DebugMonitor */
    0,                                 /* 13: reserved */
    HANDLER(buckc_fault_handler),      /* 14: PendSV */
    HANDLER(buckc_fault_handler),      /* 15: SysTick */
};
