/* The C benchmark harness: a controller's step timed with Python out of the loop.
 *
 * Compiled with the same sources as the controller FMUs (controllers/c and the generated
 * controller_config.h, data only). Reads recorded closed-loop measurements -- N rows of six
 * doubles (time, reference, output voltage, inductor current, load current, input voltage), as
 * cosim/benchmark_harness writes them -- replays them through the controller's step `repeats`
 * times (reset before each pass) and prints, after all passes, one line per step of every pass:
 *
 *     <ns of the step> <duty> <candidate evaluations> <refinement passes> <solver> <box-QP iterations> <updated>
 *
 * (solver: 0 the search, 1 the real-time iteration; both 0 for the PI and the explicit policy; updated: 1
 * where the adaptive NNPC's recursive least squares updated the output layer in the step -- the header
 * of an adaptive NNPC defines ADAPTIVE_CONTROLLER and the adaptation's configuration)
 *
 * (the caller computes p50 / p99). Timer: clock_gettime(CLOCK_MONOTONIC), read around the step
 * only; results are kept in memory allocated before the first step and printed at the end.
 *
 * Built with -DHARNESS_COUNT_INSTRUCTIONS and run under valgrind --tool=callgrind --collect-atstart=no, it
 * collects each step's instructions alone and dumps them, one profile per step (the ns column is then
 * callgrind's slowed clock, not the step's: cosim/benchmark_harness/instruction_count.py reads the dumps). */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "adaptation.h"
#include "controller_config.h"
#include "explicit_policy.h"
#include "pi.h"
#include "predictive.h"

#ifdef HARNESS_COUNT_INSTRUCTIONS
#include <valgrind/callgrind.h>
#define STEP_BEGIN() CALLGRIND_TOGGLE_COLLECT
#define STEP_END() do { CALLGRIND_TOGGLE_COLLECT; CALLGRIND_DUMP_STATS; } while (0)
#else
#define STEP_BEGIN() ((void)0)
#define STEP_END() ((void)0)
#endif

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
    int *updated = (int *)malloc((total + 1) * sizeof(int)), *reweighted = (int *)malloc((total + 1) * sizeof(int));
    if (ns == NULL || duties == NULL || evaluations == NULL || passes == NULL || solvers == NULL || qp == NULL
        || updated == NULL || reweighted == NULL)
        return 2;
    const char *what = NULL;
#ifdef ADAPTIVE_CONTROLLER
    static BuckcAdaptive adaptive; /* big: not on the stack */
    int status = buckc_adaptive_init(&adaptive, &PREDICTIVE_CONFIG, &ADAPTATION_CONFIG, &what);
    const BuckcPredictiveState *s = buckc_predictive_state(buckc_adaptive_inner(&adaptive));
    const int *counters = buckc_adaptive_counters(&adaptive);
#else
    static BuckcPredictive predictive; /* big: not on the stack */
    BuckcPi pi;
    BuckcPolicy policy;
    int status = CONTROLLER_KIND == CONTROLLER_PI         ? buckc_pi_init(&pi, &PI_CONFIG, &what)
                 : CONTROLLER_KIND == CONTROLLER_EXPLICIT ? buckc_policy_init(&policy, &POLICY_CONFIG, &what)
                                                          : buckc_predictive_init(&predictive, &PREDICTIVE_CONFIG, &what);
    const BuckcPredictiveState *s = buckc_predictive_state(&predictive);
#endif
    if (status != BUCKC_OK) {
        fprintf(stderr, "the configuration is refused: %s\n", what ? what : "");
        return 2;
    }
    for (int r = 0; r < repeats; ++r) {
#ifdef ADAPTIVE_CONTROLLER
        buckc_adaptive_reset(&adaptive);
#else
        if (CONTROLLER_KIND == CONTROLLER_PI) buckc_pi_reset(&pi);
        else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) buckc_policy_reset(&policy);
        else buckc_predictive_reset(&predictive);
#endif
        for (size_t k = 0; k < rows; ++k) {
            const double *row = m + 6 * k;
            double duty = 0.0;
#ifdef ADAPTIVE_CONTROLLER
            int updates = counters[BUCKC_ADAPT_UPDATES];
#endif
            long long start = now_ns();
            STEP_BEGIN();
#ifdef ADAPTIVE_CONTROLLER
            {
                BuckcMeasurement x = {row[0], row[1], row[2], row[3], row[4], row[5]};
                if (buckc_adaptive_step(&adaptive, &x, &duty) != BUCKC_OK) return 3;
            }
#else
            if (CONTROLLER_KIND == CONTROLLER_PI) {
                duty = buckc_pi_step(&pi, row[1], row[2]);
            } else if (CONTROLLER_KIND == CONTROLLER_EXPLICIT) {
                BuckcMeasurement x = {row[0], row[1], row[2], row[3], row[4], row[5]};
                if (buckc_policy_step(&policy, &x, &duty) != BUCKC_OK) return 3;
            } else {
                BuckcMeasurement x = {row[0], row[1], row[2], row[3], row[4], row[5]};
                if (buckc_predictive_step(&predictive, &x, &duty) != BUCKC_OK) return 3;
            }
#endif
            STEP_END();
            long long elapsed = now_ns() - start;
            size_t i = (size_t)r * rows + k;
            int predictive_kind = CONTROLLER_KIND == CONTROLLER_PREDICTIVE || CONTROLLER_KIND == CONTROLLER_ADAPTIVE;
            ns[i] = elapsed;
            duties[i] = duty;
            evaluations[i] = predictive_kind ? s->evaluations : 0;
            passes[i] = predictive_kind ? s->passes : 0;
            solvers[i] = predictive_kind ? s->last_solver : 0;
            qp[i] = predictive_kind ? s->qp_iterations : 0;
            reweighted[i] = predictive_kind ? s->reweighted : 0;
#ifdef ADAPTIVE_CONTROLLER
            updated[i] = counters[BUCKC_ADAPT_UPDATES] > updates;
#else
            updated[i] = 0;
#endif
        }
    }
    for (size_t i = 0; i < total; ++i)
        printf("%lld %.17g %d %d %d %d %d %d\n", ns[i], duties[i], evaluations[i], passes[i], solvers[i], qp[i],
               updated[i], reweighted[i]);
    free(m);
    free(ns);
    free(duties);
    free(evaluations);
    free(passes);
    free(solvers);
    free(qp);
    free(updated);
    free(reweighted);
    return 0;
}
