/* The two halves of the piezo-fmu native FMI runtime and what they share.
 *
 * fmi2_runtime.c -> binaries/linux64/<modelIdentifier>.so   (libc and libdl only)
 *     Every FMI 2.0 co-simulation function: argument and instance checks, logging, the FMU state
 *     handles, and fmi2SetReal/fmi2GetReal of inputs and outputs straight from the slave's
 *     shared buffer. It loads the Python library (RTLD_GLOBAL, before Python starts) and then
 * fmi2_bridge.c  -> binaries/linux64/piezo_fmu_bridge.so     (Python's C API, no libpython link)
 *     Starts Python once per process (or uses the host's), keeps one thread state per host
 *     thread, and calls the slave's entry points (fmu_src/nativeslave.py, protocol PZ_PROTOCOL).
 *
 * The bridge exports one symbol, PZ_BRIDGE_SYMBOL, and is loaded RTLD_GLOBAL, so the first FMU
 * of a process loads it and every later FMU (another copy of the runtime, from another folder)
 * finds it with dlsym(RTLD_DEFAULT) and shares it: one interpreter start, one lock, one set of
 * thread states. Nothing is ever unloaded or finalized (see fmi2_bridge.c).
 */
#ifndef PIEZO_FMU_RUNTIME_H
#define PIEZO_FMU_RUNTIME_H

#include <stdint.h>

#include "fmi2.h"

#define PZ_PROTOCOL 1                          /* must equal nativeslave.PROTOCOL */
#define PZ_BRIDGE_SYMBOL "piezo_fmu_bridge_1"  /* versioned with the protocol */
#define PZ_BRIDGE_FILE "piezo_fmu_bridge.so"
#define PZ_CONFIG_FILE "piezo_runtime.cfg"     /* in resources/, written by piezo_fmu.builder.runtime */
#define PZ_PATH_MAX 4096

/* overrides of what the build recorded (the README documents them) */
#define PZ_ENV_LIBPYTHON "PIEZO_FMU_LIBPYTHON"
#define PZ_ENV_HOME "PIEZO_FMU_PYTHONHOME"
#define PZ_ENV_PATH "PIEZO_FMU_PYTHONPATH"

enum { PZ_REAL, PZ_INTEGER, PZ_BOOLEAN, PZ_STRING };
enum { PZ_CTL_FAST_GET, PZ_CTL_FAST_SET };

/* resources/piezo_runtime.cfg, with the environment's overrides applied */
typedef struct pz_config {
    char python_version[32];      /* "3.11": the host's Python must have the same minor version */
    char libpython[PZ_PATH_MAX];  /* loaded when the process has no Python yet */
    char home[PZ_PATH_MAX];       /* PyConfig.home of an interpreter the runtime starts */
    char executable[PZ_PATH_MAX]; /* sys.executable there */
    char *paths;                  /* its module search path, entries separated by '\n' */
    char module[256];             /* the slave script's module (in resources/) */
    char cls[256];                /* the slave class in it */
    char guid[128];               /* modelDescription.xml's guid */
    char resources[PZ_PATH_MAX];  /* the resources folder of this FMU */
    const char *libpython_from;   /* "recorded at build time" or the variable's name */
} pz_config;

typedef struct pz_instance pz_instance;
typedef void (*pz_log_fn)(pz_instance *inst, fmi2Status status, const char *category, const char *text);

/* One FMU instance (fmi2Component). Owned by fmi2_runtime.c; the bridge fills the fast path and
   `py`, and reports through `log`. */
struct pz_instance {
    uint32_t magic;
    char *name;
    fmi2CallbackFunctions cb;     /* a copy: FMI 2.0 only guarantees the functions, not the struct */
    unsigned debug_mask;          /* debug (fmi2OK) categories enabled, see fmi2SetDebugLogging */
    int fatal;                    /* after fmi2Fatal only fmi2FreeInstance is allowed */
    double last_time;             /* end of the last successful step (fmi2LastSuccessfulTime) */
    pz_log_fn log;
    /* the fast path: inputs, then outputs, in the slave's array('d'); ctl says what may be served
       from it in the slave's current mode; slot[vr] is the index in io, -1 for other variables */
    double *io;
    const int32_t *ctl;
    int n_in, n_io;
    uint32_t n_slot;
    int32_t *slot;
    void *py;                     /* the bridge's part */
};

typedef struct pz_bridge {
    int protocol;
    /* start Python (or adopt the host's) once per process; 0 on success, else a message in err */
    int (*start)(const pz_config *cfg, char *err, size_t errlen);
    fmi2Status (*instantiate)(pz_instance *inst, const pz_config *cfg, int visible);
    void (*free_instance)(pz_instance *inst);
    fmi2Status (*call)(pz_instance *inst, const char *method);   /* no arguments, no result */
    fmi2Status (*setup)(pz_instance *inst, int tol_defined, double tol, double start, int stop_defined,
                        double stop);
    fmi2Status (*reset)(pz_instance *inst);
    fmi2Status (*do_step)(pz_instance *inst, double t, double h);
    fmi2Status (*set_values)(pz_instance *inst, int type, const fmi2ValueReference *vr, size_t n,
                             const void *values);
    fmi2Status (*get_values)(pz_instance *inst, int type, const fmi2ValueReference *vr, size_t n, void *values);
    fmi2Status (*get_state)(pz_instance *inst, fmi2FMUstate *state);
    fmi2Status (*set_state)(pz_instance *inst, fmi2FMUstate state);
    fmi2Status (*free_state)(pz_instance *inst, fmi2FMUstate *state);
    fmi2Status (*serialized_size)(pz_instance *inst, fmi2FMUstate state, size_t *size);
    fmi2Status (*serialize)(pz_instance *inst, fmi2FMUstate state, fmi2Byte *bytes, size_t size);
    fmi2Status (*deserialize)(pz_instance *inst, const fmi2Byte *bytes, size_t size, fmi2FMUstate *state);
} pz_bridge;

#endif
