/* One piecewise-constant scenario signal, as the generated scenario_config.h declares it. */
#ifndef SCENARIO_SCHEDULE_H
#define SCENARIO_SCHEDULE_H

typedef struct {
    int count;            /* changes, >= 1: the first is the initial value */
    const double *times;  /* [s] FMU (plant) time of each change, ascending */
    const double *values; /* the signal's value from that time on (V or Ohm) */
} ScenarioSchedule;

#endif
