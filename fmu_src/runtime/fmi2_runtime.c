/* piezo-fmu native FMI runtime, FMI layer: binaries/linux64/<modelIdentifier>.so of every FMU.
 *
 * Needs only libc and libdl, so any FMI 2.0 host can load it (dlopen, RTLD_NOW or not). At the
 * first fmi2Instantiate of a process it makes a Python library available with its symbols
 * global (the host's own, or the one the build recorded, see PZ_ENV_LIBPYTHON) and loads the
 * Python half (fmi2_bridge.c) beside this file; see runtime.h for the split.
 *
 * Every function checks its instance and arguments first and answers with a status and a logged
 * message. fmi2SetReal/fmi2GetReal of the continuous inputs and outputs are served here from the
 * slave's shared buffer without entering Python whenever the slave's mode allows it (ctl), and
 * inputs are checked finite first; everything else goes to the bridge.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "runtime.h"

#define PZ_MAGIC 0x505a4649u   /* a live instance */
#define PZ_DEAD 0x44454144u    /* what fmi2FreeInstance leaves behind */

/* the log categories of the modelDescription (<LogCategories>, written by pythonfmu) */
static const char *const CATEGORIES[] = {"logStatusWarning", "logStatusDiscard", "logStatusError",
                                         "logStatusFatal", "logAll"};
#define N_CATEGORIES 5
#define ALL_CATEGORIES ((1u << N_CATEGORIES) - 1)
#define LOG_ALL_BIT (1u << 4)

static pthread_mutex_t load_lock = PTHREAD_MUTEX_INITIALIZER;
static const pz_bridge *bridge;   /* the process's bridge, set by the first successful fmi2Instantiate */
static const char anchor;         /* an address inside this library, for dladdr */

/* ---------------------------------------------------------------------------------------------
 * logging
 * ------------------------------------------------------------------------------------------- */

static int category_index(const char *category)
{
    for (int i = 0; category && i < N_CATEGORIES; i++)
        if (strcmp(category, CATEGORIES[i]) == 0)
            return i;
    return -1;
}

static const char *status_category(fmi2Status status)
{
    switch (status) {
    case fmi2Warning: return CATEGORIES[0];
    case fmi2Discard: return CATEGORIES[1];
    case fmi2Error: return CATEGORIES[2];
    case fmi2Fatal: return CATEGORIES[3];
    default: return CATEGORIES[4];
    }
}

/* The one way a message reaches the host. Warnings and worse always go out (the standard expects
   the logger to have shown them when a function returns such a status); debug messages (fmi2OK)
   only for the categories enabled with loggingOn or fmi2SetDebugLogging. The message argument is
   a printf format for the host, and '#' is FMI's variable-reference escape: both are doubled. */
static void emit(pz_instance *I, fmi2Status status, const char *category, const char *text)
{
    if (!I->cb.logger || !text)
        return;
    if (!category)
        category = status_category(status);
    if (status == fmi2OK || status == fmi2Pending) {
        int i = category_index(category);
        unsigned bit = i < 0 ? LOG_ALL_BIT : 1u << i;
        if (!(I->debug_mask & (bit | LOG_ALL_BIT)))
            return;
    }
    size_t n = 0;
    for (const char *p = text; *p; p++)
        n += (*p == '%' || *p == '#') ? 2 : 1;
    char *buf = malloc(n + 1);
    if (!buf) {
        I->cb.logger(I->cb.componentEnvironment, I->name, status, category, "(out of memory for a message)");
        return;
    }
    char *q = buf;
    for (const char *p = text; *p; p++) {
        if (*p == '%' || *p == '#')
            *q++ = *p;
        *q++ = *p;
    }
    *q = '\0';
    I->cb.logger(I->cb.componentEnvironment, I->name, status, category, buf);
    free(buf);
}

static void logf_(pz_instance *I, fmi2Status status, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void logf_(pz_instance *I, fmi2Status status, const char *fmt, ...)
{
    char buf[PZ_PATH_MAX + 1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    emit(I, status, NULL, buf);
}

/* ---------------------------------------------------------------------------------------------
 * instance checks
 * ------------------------------------------------------------------------------------------- */

/* The instance behind c, or NULL with the status to return. FMI 2.0 gives no way to report on an
   invalid component (no callbacks are known), so that case only says so on stderr. After a
   fmi2Fatal the standard allows no further call but fmi2FreeInstance. */
static pz_instance *use(fmi2Component c, const char *fn, fmi2Status *status)
{
    pz_instance *I = c;
    if (!I || I->magic != PZ_MAGIC) {
        fprintf(stderr, "piezo-fmu runtime: %s called with %s fmi2Component %p\n", fn,
                I && I->magic == PZ_DEAD ? "a freed" : "an invalid", c);
        *status = fmi2Error;
        return NULL;
    }
    if (I->fatal) {
        logf_(I, fmi2Fatal, "%s: not allowed after an earlier call returned fmi2Fatal "
              "(only fmi2FreeInstance is)", fn);
        *status = fmi2Fatal;
        return NULL;
    }
    return I;
}

#define USE(fn)                                                                                    \
    fmi2Status status_;                                                                            \
    pz_instance *I = use(c, fn, &status_);                                                         \
    if (!I)                                                                                        \
        return status_

static fmi2Status done(pz_instance *I, fmi2Status status)
{
    if (status == fmi2Fatal)
        I->fatal = 1;
    return status;
}

static fmi2Status refuse(pz_instance *I, const char *fn, const char *why)
{
    logf_(I, fmi2Error, "%s: %s", fn, why);
    return fmi2Error;
}

/* vr/value arrays may only be null when nvr is 0 */
#define ARRAYS(fn, vr, values, nvr)                                                                \
    do {                                                                                           \
        if ((nvr) == 0)                                                                            \
            return fmi2OK;                                                                         \
        if (!(vr) || !(values))                                                                    \
            return refuse(I, fn, "vr[] or value[] is a null pointer while nvr > 0");               \
    } while (0)

/* All of vr[] are continuous Real inputs (inputs_only) or inputs/outputs of the shared buffer. */
static int all_in_buffer(const pz_instance *I, const fmi2ValueReference vr[], size_t nvr, int inputs_only)
{
    int limit = inputs_only ? I->n_in : I->n_io;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] >= I->n_slot)
            return 0;
        int32_t s = I->slot[vr[k]];
        if (s < 0 || s >= limit)
            return 0;
    }
    return 1;
}

/* ---------------------------------------------------------------------------------------------
 * configuration and loading
 * ------------------------------------------------------------------------------------------- */

static void copy(char *dst, size_t n, const char *src)
{
    snprintf(dst, n, "%s", src ? src : "");
}

static int hexval(int ch)
{
    if (ch >= '0' && ch <= '9') return ch - '0';
    if (ch >= 'a' && ch <= 'f') return ch - 'a' + 10;
    if (ch >= 'A' && ch <= 'F') return ch - 'A' + 10;
    return -1;
}

/* fmuResourceLocation -> a folder. FMI 2.0 (2.1.5): a "file" URI with an absolute path, with or
   without the authority ("file:///abs/path", "file:/abs/path", "file://localhost/abs/path");
   percent-encoded bytes are decoded. A plain absolute path is accepted too. */
static int resources_from_uri(const char *uri, char *out, size_t n)
{
    const char *p = uri;
    if (!p)
        return -1;
    if (strncmp(p, "file:", 5) == 0) {
        p += 5;
        if (p[0] == '/' && p[1] == '/') {
            const char *host = p + 2, *slash = strchr(host, '/');
            if (!slash)
                return -1;
            if (slash != host && !(slash - host == 9 && strncmp(host, "localhost", 9) == 0))
                return -1;
            p = slash;
        }
    }
    if (*p != '/')
        return -1;
    size_t k = 0;
    for (; *p && k + 1 < n; p++) {
        int hi, lo;
        if (*p == '%' && (hi = hexval(p[1])) >= 0 && (lo = hexval(p[2])) >= 0) {
            out[k++] = (char)(hi * 16 + lo);
            p += 2;
        } else {
            out[k++] = *p;
        }
    }
    if (*p)
        return -1;
    while (k > 1 && out[k - 1] == '/')
        k--;
    out[k] = '\0';
    return 0;
}

/* This library's folder (binaries/linux64). */
static int own_dir(char *out, size_t n)
{
    Dl_info info;
    if (!dladdr(&anchor, &info) || !info.dli_fname)
        return -1;
    copy(out, n, info.dli_fname);
    char *slash = strrchr(out, '/');
    if (!slash)
        return -1;
    *slash = '\0';
    return 0;
}

static int append_path(pz_config *cfg, const char *entry, size_t len)
{
    size_t old = cfg->paths ? strlen(cfg->paths) : 0;
    char *p = realloc(cfg->paths, old + len + 2);
    if (!p)
        return -1;
    if (old)
        p[old++] = '\n';
    memcpy(p + old, entry, len);
    p[old + len] = '\0';
    cfg->paths = p;
    return 0;
}

/* resources/piezo_runtime.cfg: "key=value" lines ('#' comments), "path" repeated */
static int read_config(pz_config *cfg, char *err, size_t errlen)
{
    char file[PZ_PATH_MAX + 64];
    snprintf(file, sizeof file, "%s/%s", cfg->resources, PZ_CONFIG_FILE);
    FILE *f = fopen(file, "r");
    if (!f) {
        snprintf(err, errlen, "cannot read %s (the FMU was not built with the piezo-fmu runtime, or its "
                 "resources folder is not where fmuResourceLocation points)", file);
        return -1;
    }
    char line[PZ_PATH_MAX + 64];
    int protocol = -1;
    while (fgets(line, sizeof line, f)) {
        size_t len = strcspn(line, "\r\n");
        line[len] = '\0';
        char *eq = strchr(line, '=');
        if (line[0] == '#' || !eq)
            continue;
        *eq = '\0';
        const char *key = line, *value = eq + 1;
        if (strcmp(key, "protocol") == 0) protocol = atoi(value);
        else if (strcmp(key, "python_version") == 0) copy(cfg->python_version, sizeof cfg->python_version, value);
        else if (strcmp(key, "libpython") == 0) copy(cfg->libpython, sizeof cfg->libpython, value);
        else if (strcmp(key, "home") == 0) copy(cfg->home, sizeof cfg->home, value);
        else if (strcmp(key, "executable") == 0) copy(cfg->executable, sizeof cfg->executable, value);
        else if (strcmp(key, "module") == 0) copy(cfg->module, sizeof cfg->module, value);
        else if (strcmp(key, "class") == 0) copy(cfg->cls, sizeof cfg->cls, value);
        else if (strcmp(key, "guid") == 0) copy(cfg->guid, sizeof cfg->guid, value);
        else if (strcmp(key, "path") == 0 && append_path(cfg, value, strlen(value)) != 0) {
            fclose(f);
            snprintf(err, errlen, "out of memory reading %s", file);
            return -1;
        }
    }
    fclose(f);
    if (protocol != PZ_PROTOCOL || !cfg->module[0] || !cfg->cls[0] || !cfg->python_version[0]) {
        snprintf(err, errlen, "%s: protocol %d, module '%s', class '%s', Python '%s': not what this "
                 "runtime (protocol %d) needs; rebuild the FMU", file, protocol, cfg->module, cfg->cls,
                 cfg->python_version, PZ_PROTOCOL);
        return -1;
    }
    cfg->libpython_from = "recorded at build time";
    const char *env = getenv(PZ_ENV_LIBPYTHON);
    if (env && *env) {
        copy(cfg->libpython, sizeof cfg->libpython, env);
        cfg->libpython_from = PZ_ENV_LIBPYTHON;
    }
    env = getenv(PZ_ENV_HOME);
    if (env && *env) {
        /* another Python installation: used as it is (its own default module path and site) unless
           the module path is given too */
        copy(cfg->home, sizeof cfg->home, env);
        free(cfg->paths);
        cfg->paths = NULL;
    }
    env = getenv(PZ_ENV_PATH);
    if (env && *env) {
        free(cfg->paths);
        cfg->paths = NULL;
        for (const char *p = env; *p;) {
            size_t len = strcspn(p, ":");
            if (len && append_path(cfg, p, len) != 0)
                return -1;
            p += len + (p[len] == ':');
        }
    }
    return 0;
}

/* The process-wide bridge: another FMU's (already global), else ours, after making a Python
   library global. Called under load_lock. */
static const pz_bridge *load_bridge(const pz_config *cfg, char *err, size_t errlen)
{
    const pz_bridge *b = dlsym(RTLD_DEFAULT, PZ_BRIDGE_SYMBOL);
    if (b)
        return b;
    if (!dlsym(RTLD_DEFAULT, "Py_IsInitialized")) {
        /* no Python in the process yet: load one with its symbols global before Python starts
           (NumPy's extension modules resolve the C API from the global scope) */
        if (!cfg->libpython[0]) {
            snprintf(err, errlen, "no Python library is recorded in %s/%s; set %s to a libpython%s.so",
                     cfg->resources, PZ_CONFIG_FILE, PZ_ENV_LIBPYTHON, cfg->python_version);
            return NULL;
        }
        if (!dlopen(cfg->libpython, RTLD_NOW | RTLD_GLOBAL)) {
            const char *why = dlerror();
            snprintf(err, errlen, "cannot load the Python library %s (%s): %s; set %s to the path of a "
                     "libpython%s.so with numpy installed", cfg->libpython, cfg->libpython_from,
                     why ? why : "?", PZ_ENV_LIBPYTHON, cfg->python_version);
            return NULL;
        }
    }
    const char *(*version)(void) = (const char *(*)(void))dlsym(RTLD_DEFAULT, "Py_GetVersion");
    const char *v = version ? version() : "?";
    size_t n = strlen(cfg->python_version);
    if (strncmp(v, cfg->python_version, n) != 0 || v[n] != '.') {
        snprintf(err, errlen, "the Python in this process is %.20s, the FMU was built for Python %s "
                 "(loaded: %s, %s)", v, cfg->python_version, cfg->libpython, cfg->libpython_from);
        return NULL;
    }
    char path[PZ_PATH_MAX + 64];
    if (own_dir(path, PZ_PATH_MAX) != 0) {
        snprintf(err, errlen, "cannot find the folder of the FMU's binary (dladdr)");
        return NULL;
    }
    strcat(path, "/" PZ_BRIDGE_FILE);
    void *h = dlopen(path, RTLD_NOW | RTLD_GLOBAL);
    if (!h) {
        const char *why = dlerror();
        snprintf(err, errlen, "cannot load %s: %s", path, why ? why : "?");
        return NULL;
    }
    b = dlsym(h, PZ_BRIDGE_SYMBOL);
    if (!b || b->protocol != PZ_PROTOCOL) {
        snprintf(err, errlen, "%s does not provide %s of protocol %d", path, PZ_BRIDGE_SYMBOL, PZ_PROTOCOL);
        return NULL;
    }
    return b;
}

/* ---------------------------------------------------------------------------------------------
 * inquiry, creation, destruction, logging (FMI 2.0 section 2.1.4-2.1.5)
 * ------------------------------------------------------------------------------------------- */

const char *fmi2GetTypesPlatform(void)
{
    return "default";   /* the standard's platform types (fmi2.h) */
}

const char *fmi2GetVersion(void)
{
    return "2.0";
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn)
{
    /* FMI 2.0: a null return means failure, with the reason given to functions->logger. The
       struct pointer is only valid during this call: the callbacks are copied. */
    pz_instance tmp = {0};
    tmp.name = (char *)(instanceName && *instanceName ? instanceName : "?");
    if (!functions || !functions->logger) {
        fprintf(stderr, "piezo-fmu runtime: fmi2Instantiate(%s): no logger callback given\n", tmp.name);
        return NULL;
    }
    tmp.cb = *functions;
    tmp.debug_mask = loggingOn ? ALL_CATEGORIES : 0;
    const char *blank = instanceName;
    while (blank && *blank && (*blank == ' ' || *blank == '\t' || *blank == '\n' || *blank == '\r'))
        blank++;
    if (!instanceName || !*blank) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: instanceName must be a non-empty string");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: this is a co-simulation FMU; fmuType %d is not supported",
              (int)fmuType);
        return NULL;
    }
    if (!fmuGUID) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: fmuGUID is a null pointer");
        return NULL;
    }
    pz_config cfg = {0};
    char err[2 * PZ_PATH_MAX];
    if (resources_from_uri(fmuResourceLocation, cfg.resources, sizeof cfg.resources) != 0 ||
        access(cfg.resources, R_OK) != 0) {
        /* not a usable file URI: the resources folder of the FMU this binary was unpacked from */
        char dir[PZ_PATH_MAX - 32];
        if (own_dir(dir, sizeof dir) != 0) {
            logf_(&tmp, fmi2Error, "fmi2Instantiate: fmuResourceLocation '%s' is not a file URI of a folder",
                  fmuResourceLocation ? fmuResourceLocation : "(null)");
            return NULL;
        }
        snprintf(cfg.resources, sizeof cfg.resources, "%s/../../resources", dir);
        logf_(&tmp, fmi2Warning, "fmi2Instantiate: fmuResourceLocation '%s' is not a file URI of a folder; "
              "using %s", fmuResourceLocation ? fmuResourceLocation : "(null)", cfg.resources);
    }
    if (read_config(&cfg, err, sizeof err) != 0) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: %s", err);
        free(cfg.paths);
        return NULL;
    }
    if (strcmp(fmuGUID, cfg.guid) != 0) {
        /* FMI 2.0: the GUID must be identical to the one stored in the FMU's C code */
        logf_(&tmp, fmi2Error, "fmi2Instantiate: fmuGUID %s does not match this FMU's %s (the "
              "modelDescription.xml and the binary come from different builds)", fmuGUID, cfg.guid);
        free(cfg.paths);
        return NULL;
    }
    pthread_mutex_lock(&load_lock);
    if (!bridge)
        bridge = load_bridge(&cfg, err, sizeof err);
    const pz_bridge *b = bridge;
    pthread_mutex_unlock(&load_lock);
    if (!b || b->start(&cfg, err, sizeof err) != 0) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: %s", err);
        free(cfg.paths);
        return NULL;
    }
    pz_instance *I = calloc(1, sizeof *I);
    char *name = strdup(instanceName);
    if (!I || !name) {
        logf_(&tmp, fmi2Error, "fmi2Instantiate: out of memory");
        free(I);
        free(name);
        free(cfg.paths);
        return NULL;
    }
    *I = tmp;
    I->name = name;
    I->magic = PZ_MAGIC;
    I->log = emit;
    fmi2Status st = b->instantiate(I, &cfg, visible != fmi2False);
    free(cfg.paths);
    if (st > fmi2Warning) {
        I->magic = PZ_DEAD;
        free(I->name);
        free(I);
        return NULL;
    }
    return I;
}

void fmi2FreeInstance(fmi2Component c)
{
    /* FMI 2.0: a null pointer is ignored; allowed in every state, also after fmi2Fatal */
    pz_instance *I = c;
    if (!I)
        return;
    if (I->magic != PZ_MAGIC) {
        fprintf(stderr, "piezo-fmu runtime: fmi2FreeInstance called with %s fmi2Component %p\n",
                I->magic == PZ_DEAD ? "a freed" : "an invalid", c);
        return;
    }
    bridge->free_instance(I);
    I->magic = PZ_DEAD;
    free(I->name);
    free(I);
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    USE("fmi2SetDebugLogging");
    /* nCategories == 0: loggingOn applies to all categories; else to the named ones, which must be
       those of <LogCategories> */
    if (nCategories == 0) {
        I->debug_mask = loggingOn ? ALL_CATEGORIES : 0;
        return fmi2OK;
    }
    if (!categories)
        return refuse(I, "fmi2SetDebugLogging", "categories is a null pointer while nCategories > 0");
    fmi2Status st = fmi2OK;
    for (size_t k = 0; k < nCategories; k++) {
        int i = category_index(categories[k]);
        if (i < 0) {
            logf_(I, fmi2Warning, "fmi2SetDebugLogging: unknown log category '%s' ignored (known: "
                  "logStatusWarning, logStatusDiscard, logStatusError, logStatusFatal, logAll)",
                  categories[k] ? categories[k] : "(null)");
            st = fmi2Warning;
            continue;
        }
        if (loggingOn)
            I->debug_mask |= 1u << i;
        else
            I->debug_mask &= ~(1u << i);
    }
    return st;
}

/* ---------------------------------------------------------------------------------------------
 * initialization, termination, reset (FMI 2.0 section 2.1.6); the mode rules are the slave's
 * ------------------------------------------------------------------------------------------- */

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    USE("fmi2SetupExperiment");
    fmi2Status st = bridge->setup(I, toleranceDefined != fmi2False, tolerance, startTime,
                                  stopTimeDefined != fmi2False, stopTime);
    if (st <= fmi2Warning)
        I->last_time = startTime;
    return done(I, st);
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    USE("fmi2EnterInitializationMode");
    return done(I, bridge->call(I, "enter_initialization_mode"));
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    USE("fmi2ExitInitializationMode");
    return done(I, bridge->call(I, "exit_initialization_mode"));
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    USE("fmi2Terminate");
    return done(I, bridge->call(I, "terminate"));
}

fmi2Status fmi2Reset(fmi2Component c)
{
    USE("fmi2Reset");
    /* FMI 2.0: the instance goes into the state after fmi2Instantiate (a new slave object) */
    fmi2Status st = bridge->reset(I);
    if (st <= fmi2Warning)
        I->last_time = 0.0;
    return done(I, st);
}

/* ---------------------------------------------------------------------------------------------
 * values (FMI 2.0 section 2.1.7): an unknown value reference or a variable that may not be set
 * must give fmi2Error (the slave's checked path says which and why)
 * ------------------------------------------------------------------------------------------- */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[])
{
    USE("fmi2GetReal");
    ARRAYS("fmi2GetReal", vr, value, nvr);
    if (I->ctl && I->ctl[PZ_CTL_FAST_GET] && all_in_buffer(I, vr, nvr, 0)) {
        for (size_t k = 0; k < nvr; k++)
            value[k] = I->io[I->slot[vr[k]]];
        return fmi2OK;
    }
    return done(I, bridge->get_values(I, PZ_REAL, vr, nvr, value));
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[])
{
    USE("fmi2SetReal");
    ARRAYS("fmi2SetReal", vr, value, nvr);
    if (I->ctl && I->ctl[PZ_CTL_FAST_SET] && all_in_buffer(I, vr, nvr, 1)) {
        size_t k = 0;
        while (k < nvr && value[k] - value[k] == 0.0)   /* finite (NaN and inf give NaN) */
            k++;
        if (k == nvr) {
            for (k = 0; k < nvr; k++)
                I->io[I->slot[vr[k]]] = value[k];
            return fmi2OK;
        }
        /* a non-finite input: the slave refuses it with a message naming the variable */
    }
    return done(I, bridge->set_values(I, PZ_REAL, vr, nvr, value));
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])
{
    USE("fmi2GetInteger");
    ARRAYS("fmi2GetInteger", vr, value, nvr);
    return done(I, bridge->get_values(I, PZ_INTEGER, vr, nvr, value));
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[])
{
    USE("fmi2SetInteger");
    ARRAYS("fmi2SetInteger", vr, value, nvr);
    return done(I, bridge->set_values(I, PZ_INTEGER, vr, nvr, value));
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[])
{
    USE("fmi2GetBoolean");
    ARRAYS("fmi2GetBoolean", vr, value, nvr);
    return done(I, bridge->get_values(I, PZ_BOOLEAN, vr, nvr, value));
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[])
{
    USE("fmi2SetBoolean");
    ARRAYS("fmi2SetBoolean", vr, value, nvr);
    return done(I, bridge->set_values(I, PZ_BOOLEAN, vr, nvr, value));
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[])
{
    USE("fmi2GetString");
    ARRAYS("fmi2GetString", vr, value, nvr);
    /* the strings stay valid until the next call of this function on the instance */
    return done(I, bridge->get_values(I, PZ_STRING, vr, nvr, value));
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[])
{
    USE("fmi2SetString");
    ARRAYS("fmi2SetString", vr, value, nvr);
    for (size_t k = 0; k < nvr; k++)
        if (!value[k])
            return refuse(I, "fmi2SetString", "value[] holds a null pointer");
    return done(I, bridge->set_values(I, PZ_STRING, vr, nvr, value));
}

/* ---------------------------------------------------------------------------------------------
 * FMU state (FMI 2.0 section 2.1.8): canGetAndSetFMUstate and canSerializeFMUstate are true. A
 * state belongs to the instance that made it and is freed with it at the latest.
 * ------------------------------------------------------------------------------------------- */

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    USE("fmi2GetFMUstate");
    if (!FMUstate)
        return refuse(I, "fmi2GetFMUstate", "FMUstate is a null pointer");
    /* *FMUstate == NULL: a new state; else a state of ours to overwrite */
    return done(I, bridge->get_state(I, FMUstate));
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate)
{
    USE("fmi2SetFMUstate");
    if (!FMUstate)
        return refuse(I, "fmi2SetFMUstate", "FMUstate is a null pointer");
    return done(I, bridge->set_state(I, FMUstate));
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    USE("fmi2FreeFMUstate");
    /* a null pointer is ignored; the state pointer comes back as null */
    if (!FMUstate || !*FMUstate)
        return fmi2OK;
    return done(I, bridge->free_state(I, FMUstate));
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size)
{
    USE("fmi2SerializedFMUstateSize");
    if (!FMUstate || !size)
        return refuse(I, "fmi2SerializedFMUstateSize", "FMUstate or size is a null pointer");
    return done(I, bridge->serialized_size(I, FMUstate, size));
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size)
{
    USE("fmi2SerializeFMUstate");
    if (!FMUstate || !serializedState)
        return refuse(I, "fmi2SerializeFMUstate", "FMUstate or serializedState is a null pointer");
    return done(I, bridge->serialize(I, FMUstate, serializedState, size));
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate)
{
    USE("fmi2DeSerializeFMUstate");
    if (!serializedState || !FMUstate)
        return refuse(I, "fmi2DeSerializeFMUstate", "serializedState or FMUstate is a null pointer");
    return done(I, bridge->deserialize(I, serializedState, size, FMUstate));
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[])
{
    USE("fmi2GetDirectionalDerivative");
    (void)vUnknown_ref, (void)nUnknown, (void)vKnown_ref, (void)nKnown, (void)dvKnown, (void)dvUnknown;
    /* providesDirectionalDerivative is false in the modelDescription */
    return refuse(I, "fmi2GetDirectionalDerivative", "not provided by this FMU "
                  "(providesDirectionalDerivative=false)");
}

/* ---------------------------------------------------------------------------------------------
 * co-simulation (FMI 2.0 section 4.2)
 * ------------------------------------------------------------------------------------------- */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    USE("fmi2SetRealInputDerivatives");
    (void)vr, (void)nvr, (void)order, (void)value;
    /* canInterpolateInputs is false: inputs are held over the communication step */
    return refuse(I, "fmi2SetRealInputDerivatives", "not supported (canInterpolateInputs=false: "
                  "inputs are held constant over a communication step)");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{
    USE("fmi2GetRealOutputDerivatives");
    (void)vr, (void)nvr, (void)order, (void)value;
    /* maxOutputDerivativeOrder is 0 */
    return refuse(I, "fmi2GetRealOutputDerivatives", "not supported (maxOutputDerivativeOrder=0)");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    USE("fmi2DoStep");
    (void)noSetFMUStatePriorToCurrentPoint;   /* states are kept by value: nothing to drop */
    /* synchronous: never fmi2Pending, so stepFinished is never called */
    fmi2Status st = bridge->do_step(I, currentCommunicationPoint, communicationStepSize);
    if (st <= fmi2Warning)
        I->last_time = currentCommunicationPoint + communicationStepSize;
    return done(I, st);
}

fmi2Status fmi2CancelStep(fmi2Component c)
{
    USE("fmi2CancelStep");
    /* only meaningful after fmi2DoStep returned fmi2Pending, which it never does */
    return refuse(I, "fmi2CancelStep", "no asynchronous step to cancel (fmi2DoStep is synchronous)");
}

/* FMI 2.0 section 4.2.3: fmi2Discard when the slave cannot give the requested status */
static fmi2Status no_status(pz_instance *I, const char *fn, fmi2StatusKind s)
{
    logf_(I, fmi2Discard, "%s: status kind %d is not available (fmi2DoStep is synchronous; use "
          "fmi2GetRealStatus(fmi2LastSuccessfulTime) or fmi2GetBooleanStatus(fmi2Terminated))", fn, (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{
    USE("fmi2GetStatus");
    if (!value)
        return refuse(I, "fmi2GetStatus", "value is a null pointer");
    return no_status(I, "fmi2GetStatus", s);
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    USE("fmi2GetRealStatus");
    if (!value)
        return refuse(I, "fmi2GetRealStatus", "value is a null pointer");
    if (s != fmi2LastSuccessfulTime)
        return no_status(I, "fmi2GetRealStatus", s);
    *value = I->last_time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{
    USE("fmi2GetIntegerStatus");
    if (!value)
        return refuse(I, "fmi2GetIntegerStatus", "value is a null pointer");
    return no_status(I, "fmi2GetIntegerStatus", s);
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{
    USE("fmi2GetBooleanStatus");
    if (!value)
        return refuse(I, "fmi2GetBooleanStatus", "value is a null pointer");
    if (s != fmi2Terminated)
        return no_status(I, "fmi2GetBooleanStatus", s);
    *value = fmi2False;   /* the slave never asks to end the simulation */
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{
    USE("fmi2GetStringStatus");
    if (!value)
        return refuse(I, "fmi2GetStringStatus", "value is a null pointer");
    return no_status(I, "fmi2GetStringStatus", s);
}
