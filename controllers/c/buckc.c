/*
 * buckc.c -- status texts and struct sizes for bindings (not an algorithm file; see buckc.h).
 */
#include <string.h>

#include "buckc.h"
#include "buckc_pair.h"
#include "compensator.h"
#include "current_mode.h"
#include "explicit_policy.h"
#include "nn_model.h"
#include "pi.h"
#if BUCKC_HAVE_PREDICTIVE
#include "adaptation.h"
#include "predictive.h"
#include "predictors.h"
#endif

const char *buckc_real_name(void)
{
    return BUCKC_REAL_NAME;
}

const char *buckc_pair_backend(void)
{
    return BUCKC_PAIRS_SSE2 ? "sse2" : "scalar";
}

const char *buckc_status_text(int status)
{
    switch (status) {
    case BUCKC_OK: return "ok";
    case BUCKC_ERR_NULL: return "a required pointer is NULL";
    case BUCKC_ERR_LIMIT: return "a size is above a compile-time maximum";
    case BUCKC_ERR_INVALID: return "an invalid value";
    case BUCKC_ERR_NO_INDUCTOR_CURRENT: return "the predictive controller needs the inductor current";
    case BUCKC_ERR_ILL_CONDITIONED: return "the switched model's sensor map is ill-conditioned at this load";
    default: return "unknown status";
    }
}

size_t buckc_struct_size(const char *type_name)
{
#define SIZE(T) if (strcmp(type_name, #T) == 0) return sizeof(T)
    if (type_name == NULL)
        return 0;
    SIZE(BuckcPiConfig);
    SIZE(BuckcPi);
    SIZE(BuckcNnConfig);
    SIZE(BuckcNnShared);
    SIZE(BuckcMeasurement);
    SIZE(BuckcPolicyConfig);
    SIZE(BuckcPolicy);
#if BUCKC_HAVE_PREDICTIVE
    SIZE(BuckcCircuitParameters);
    SIZE(BuckcAveragedConfig);
    SIZE(BuckcAveragedStep);
    SIZE(BuckcSwitchedConfig);
    SIZE(BuckcSwitchedTable);
    SIZE(BuckcHorizonSettings);
    SIZE(BuckcOptimizer);
    SIZE(BuckcPredictorConfig);
    SIZE(BuckcRtiSettings);
    SIZE(BuckcPredictiveConfig);
    SIZE(BuckcPredictiveState);
    SIZE(BuckcPredictive);
    SIZE(BuckcAdaptationSettings);
    SIZE(BuckcAdaptationConfig);
#endif
    SIZE(BuckcCurrentModeConfig);
    SIZE(BuckcCurrentMode);
    SIZE(BuckcCompensatorConfig);
    SIZE(BuckcCompensator);
#undef SIZE
    return 0;
}
