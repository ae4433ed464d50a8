/* FMI 2.0 co-simulation declarations of the piezo-fmu runtime.
 *
 * Written for this project from the function signatures and type definitions in the FMI 2.0
 * standard's text (sections 2.1.2-2.1.9 and 4.2), with the standard's default platform types
 * ("default": double, int, unsigned int value references). Only what the runtime implements:
 * the common functions and the co-simulation functions, no model-exchange ones.
 */
#ifndef PIEZO_FMU_FMI2_H
#define PIEZO_FMU_FMI2_H

#include <stddef.h>

typedef void *fmi2Component;             /* an FMU instance */
typedef void *fmi2ComponentEnvironment;  /* the host's data, handed back to its callbacks */
typedef void *fmi2FMUstate;              /* a saved FMU state */
typedef unsigned int fmi2ValueReference;
typedef double fmi2Real;
typedef int fmi2Integer;
typedef int fmi2Boolean;
typedef char fmi2Char;
typedef const fmi2Char *fmi2String;
typedef char fmi2Byte;

#define fmi2True 1
#define fmi2False 0

typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef enum { fmi2ModelExchange, fmi2CoSimulation } fmi2Type;
typedef enum { fmi2DoStepStatus, fmi2PendingStatus, fmi2LastSuccessfulTime, fmi2Terminated } fmi2StatusKind;

typedef struct {
    /* message is a printf format: "%" in a text must be written "%%"; "#" is FMI's own escape */
    void (*logger)(fmi2ComponentEnvironment env, fmi2String instanceName, fmi2Status status,
                   fmi2String category, fmi2String message, ...);
    void *(*allocateMemory)(size_t nobj, size_t size);
    void (*freeMemory)(void *obj);
    void (*stepFinished)(fmi2ComponentEnvironment env, fmi2Status status);
    fmi2ComponentEnvironment componentEnvironment;
} fmi2CallbackFunctions;

#define PZ_FMI_EXPORT __attribute__((visibility("default")))

/* common functions (FMI 2.0 section 2.1) */
PZ_FMI_EXPORT const char *fmi2GetTypesPlatform(void);
PZ_FMI_EXPORT const char *fmi2GetVersion(void);
PZ_FMI_EXPORT fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                                             const fmi2String categories[]);
PZ_FMI_EXPORT fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                                            fmi2String fmuResourceLocation,
                                            const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                                            fmi2Boolean loggingOn);
PZ_FMI_EXPORT void fmi2FreeInstance(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                                             fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime);
PZ_FMI_EXPORT fmi2Status fmi2EnterInitializationMode(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2ExitInitializationMode(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2Terminate(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2Reset(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]);
PZ_FMI_EXPORT fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        fmi2Integer value[]);
PZ_FMI_EXPORT fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        fmi2Boolean value[]);
PZ_FMI_EXPORT fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       fmi2String value[]);
PZ_FMI_EXPORT fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                     const fmi2Real value[]);
PZ_FMI_EXPORT fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer value[]);
PZ_FMI_EXPORT fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Boolean value[]);
PZ_FMI_EXPORT fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2String value[]);
PZ_FMI_EXPORT fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate);
PZ_FMI_EXPORT fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate);
PZ_FMI_EXPORT fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate);
PZ_FMI_EXPORT fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size);
PZ_FMI_EXPORT fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                               size_t size);
PZ_FMI_EXPORT fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                                 fmi2FMUstate *FMUstate);
PZ_FMI_EXPORT fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                                      size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                                      size_t nKnown, const fmi2Real dvKnown[],
                                                      fmi2Real dvUnknown[]);

/* co-simulation functions (FMI 2.0 section 4.2) */
PZ_FMI_EXPORT fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                                     const fmi2Integer order[], const fmi2Real value[]);
PZ_FMI_EXPORT fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                                      const fmi2Integer order[], fmi2Real value[]);
PZ_FMI_EXPORT fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                                    fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint);
PZ_FMI_EXPORT fmi2Status fmi2CancelStep(fmi2Component c);
PZ_FMI_EXPORT fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value);
PZ_FMI_EXPORT fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value);
PZ_FMI_EXPORT fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value);
PZ_FMI_EXPORT fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value);
PZ_FMI_EXPORT fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value);

#endif
