/* The C benchmark harness: a controller's step timed with Python out of the loop.
 *
 * Compiled with the same sources as the controller FMUs (controllers/c and the generated
 * controller_config.h, data only). Reads recorded closed-loop measurements -- N rows of six
 * doubles (time, reference, output voltage, inductor current, load current, input voltage), as
 * cosim/benchmark_harness writes them -- replays them through the controller's step `repeats`
 * times (reset before each pass) and prints, after all passes, one line per step of every pass:
 *
 *     <ns of the step> <duty> <candidate evaluations> <refinement passes> <solver> <box-QP iterations>
 *
 * (solver: 0 the search, 1 the real-time iteration; both 0 for the PI and the explicit policy)
 *
 * (the caller computes p50 / p99). Timer: clock_gettime(CLOCK_MONOTONIC), read around the step
 * only; results are kept in memory allocated before the first step and printed at the end. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "controller_config.h"
#include "explicit_policy.h"
#include "pi.h"
#include "predictive.h"

static long long now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: %s MEASUREMENTS.bin REPEATS\n", argv[0]);
        return 2;
    }
    FILE *in = fopen(argv[1], "rb");
    if (in == NULL) {
        fprintf(stderr, "cannot open %s\n", argv[1]);
        return 2;
    }
    fseek(in, 0, SEEK_END);
    long bytes = ftell(in);
    fseek(in, 0, SEEK_SET);
    size_t rows = (size_t)bytes / (6 * sizeof(double));
    double *m = (double *)malloc(rows * 6 * sizeof(double)); /* set-up only: the steps allocate nothing */
    if (m == NULL || fread(m, sizeof(double), rows * 6, in) != rows * 6) {
        fprintf(stderr, "cannot read %zu rows from %s\n", rows, argv[1]);
        return 2;
    }
    fclose(in);
    int repeats = atoi(argv[2]);
    size_t total = rows * (size_t)(repeats > 0 ? repeats : 0);
    long long *ns = (long long *)malloc((total + 1) * sizeof(long long));
    double *duties = (double *)malloc((total + 1) * sizeof(double));
    int *evaluations = (int *)malloc((total + 1) * sizeof(int)), *passes = (int *)malloc((total + 1) * sizeof(int));
    int *solvers = (int *)malloc((total + 1) * sizeof(int)), *qp = (int *)malloc((total + 1) * sizeof(int));
    if (ns == NULL || duties == NULL || evaluations == NULL || passes == NULL || solvers == NULL || qp == NULL)
        return 2;
    static BuckcPredictive predictive; /* big: not on the stack */
    BuckcPi pi;
    BuckcPolicy policy;
    const char *what = NULL;
    int status = CONTROLLER_KIND == CONTROLLER_PI         ? buckc_pi_init(&pi, &PI_CONFIG, &what)
                 : CONTROLLER_KIND == CONTROLLER_EXPLICIT ? buckc_policy_init(&policy, &POLICY_CONFIG, &what)
                                                          : buckc_predictive_init(&predictive, &PREDICTIVE_CONFIG, &what);
    if (status != BUCKC_OK) {
        fprintf(stderr, "the configuration is refused: %s\n", what ? what : "");
        return 2;
    }
    for (int r = 0; r < repeats; ++r) {
        if (CONTROLLER_KIND == CONTROLLER_PI) buckc_pi_reset(&pi);
        else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) buckc_policy_reset(&policy);
        else buckc_predictive_reset(&predictive);
        for (size_t k = 0; k < rows; ++k) {
            const double *row = m + 6 * k;
            double duty = 0.0;
            long long start = now_ns();
            if (CONTROLLER_KIND == CONTROLLER_PI) {
                duty = buckc_pi_step(&pi, row[1], row[2]);
            } else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) {
                BuckcMeasurement x = {row[0], row[1], row[2], row[3], row[4], row[5]};
                if (buckc_policy_step(&policy, &x, &duty) != BUCKC_OK) return 3;
            } else {
                BuckcMeasurement x = {row[0], row[1], row[2], row[3], row[4], row[5]};
                if (buckc_predictive_step(&predictive, &x, &duty) != BUCKC_OK) return 3;
            }
            long long elapsed = now_ns() - start;
            size_t i = (size_t)r * rows + k;
            const BuckcPredictiveState *s = buckc_predictive_state(&predictive);
            ns[i] = elapsed;
            duties[i] = duty;
            evaluations[i] = CONTROLLER_KIND == CONTROLLER_PREDICTIVE ? s->evaluations : 0;
            passes[i] = CONTROLLER_KIND == CONTROLLER_PREDICTIVE ? s->passes : 0;
            solvers[i] = CONTROLLER_KIND == CONTROLLER_PREDICTIVE ? s->last_solver : 0;
            qp[i] = CONTROLLER_KIND == CONTROLLER_PREDICTIVE ? s->qp_iterations : 0;
        }
    }
    for (size_t i = 0; i < total; ++i)
        printf("%lld %.17g %d %d %d %d\n", ns[i], duties[i], evaluations[i], passes[i], solvers[i], qp[i]);
    free(m);
    free(ns);
    free(duties);
    free(evaluations);
    free(passes);
    free(solvers);
    free(qp);
    return 0;
}
