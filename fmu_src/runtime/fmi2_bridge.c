/* piezo-fmu native FMI runtime, Python half: binaries/linux64/piezo_fmu_bridge.so.
 *
 * Compiled against the building Python's headers and linked to no libpython: its Python symbols
 * resolve against the library the FMI layer made global (or the host's own Python). Loaded with
 * RTLD_GLOBAL and never unloaded, it is shared by every FMU of the process (runtime.h).
 *
 * Interpreter: started once per process with the configuration the build recorded (home, module
 * path; isolated from the environment's PYTHONHOME/PYTHONPATH and from PATH; no signal handlers,
 * no site, the host's locale untouched), or, when the process already runs Python (fmpy,
 * libcosimpy, our own master), that interpreter. It is never finalized: at fmi2FreeInstance,
 * dlclose or process exit nothing is released twice, whatever the order; after the process began
 * to exit (atexit) or after a host finalized its Python, instances are freed without touching
 * Python.
 *
 * Threads: a host thread Python has never seen gets one thread state at its first call and keeps
 * it (thread-local); the GIL is released between calls (PyEval_SaveThread), so several host
 * threads can step several instances. A caller that holds the GIL (a ctypes.PyDLL call) is served
 * as it is; other threads Python knows use PyGILState_Ensure/Release. A thread state whose thread
 * ended is deleted by the next call that holds the GIL (never from the exiting thread: it could
 * wait for a GIL held by a thread joining it).
 *
 * Errors: the slave's entry points return FMI statuses (nativeslave.py); a Python exception that
 * still escapes is logged with its type and message and gives fmi2Error. fmi2Fatal only when
 * Python is gone.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "runtime.h"

#define PZ_STATE_MAGIC 0x505a5354u   /* a live FMU state */

typedef struct pz_state pz_state;
struct pz_state {
    uint32_t magic;
    PyObject *obj;        /* the slave's state object */
    PyObject *bytes;      /* its serialization, between fmi2SerializedFMUstateSize and fmi2SerializeFMUstate */
    pz_instance *owner;
    pz_state *next;
};

typedef struct {
    PyObject *cls;        /* the slave class */
    PyObject *obj;        /* the slave */
    PyObject *step;       /* obj._rt_do_step */
    PyObject *call;       /* obj._rt_call */
    PyObject *queue;      /* obj.log_queue (a list, drained after every call) */
    Py_buffer io, ctl;    /* views that pin the slave's shared arrays */
    char *resources;
    int visible;
    pz_state *states;
    char **strings;       /* the last fmi2GetString results */
    size_t n_strings;
} pz_py;

static pthread_mutex_t start_lock = PTHREAD_MUTEX_INITIALIZER;
static int started;                      /* 1: Python usable; -1: starting it failed */
static char start_error[2048];
static PyInterpreterState *interp;       /* the interpreter the thread states below belong to */
static PyThreadState *main_ts;           /* the state of the thread that started Python, if we did */
static volatile int exiting;             /* the process is exiting: leave Python alone */
static __thread PyThreadState *thread_ts;   /* this host thread's kept thread state */
static pthread_key_t ts_key;             /* to learn that a thread with a kept state ended */
static pthread_mutex_t dead_lock = PTHREAD_MUTEX_INITIALIZER;
static PyThreadState *dead[64];          /* states of ended threads, deleted under the GIL */
static volatile int n_dead;

/* ---------------------------------------------------------------------------------------------
 * the interpreter and the GIL
 * ------------------------------------------------------------------------------------------- */

static void at_exit(void)
{
    exiting = 1;
}

static void thread_ended(void *ts)
{
    /* runs in the ending thread: only remember the state */
    pthread_mutex_lock(&dead_lock);
    if (n_dead < (int)(sizeof dead / sizeof dead[0]))
        dead[n_dead++] = ts;
    pthread_mutex_unlock(&dead_lock);
}

static void bury_dead(void)
{
    /* with the GIL held; the states belong to threads that no longer exist */
    pthread_mutex_lock(&dead_lock);
    while (n_dead > 0) {
        PyThreadState *ts = dead[--n_dead];
        PyThreadState_Clear(ts);
        PyThreadState_Delete(ts);
    }
    pthread_mutex_unlock(&dead_lock);
}

static int python_alive(void)
{
    return !exiting && started == 1 && Py_IsInitialized() && PyInterpreterState_Main() == interp;
}

enum { GIL_HELD, GIL_RESTORED, GIL_ENSURED };
typedef struct {
    int how;
    PyGILState_STATE state;
} pz_gil;

static int enter(pz_gil *g)
{
    if (!python_alive())
        return -1;
    if (PyGILState_Check()) {
        g->how = GIL_HELD;                 /* the caller holds the GIL (a PyDLL call) */
    } else if (thread_ts) {
        PyEval_RestoreThread(thread_ts);   /* this thread's kept state */
        g->how = GIL_RESTORED;
    } else if (!PyGILState_GetThisThreadState()) {
        PyGILState_Ensure();               /* a thread Python has never seen: its state is kept */
        thread_ts = PyThreadState_Get();
        pthread_setspecific(ts_key, thread_ts);
        g->how = GIL_RESTORED;
    } else {
        g->state = PyGILState_Ensure();    /* a thread Python knows (the host's own) */
        g->how = GIL_ENSURED;
    }
    if (n_dead)
        bury_dead();
    return 0;
}

static void leave(pz_gil *g)
{
    if (g->how == GIL_RESTORED)
        PyEval_SaveThread();
    else if (g->how == GIL_ENSURED)
        PyGILState_Release(g->state);
}

static int set_string(PyConfig *config, wchar_t **field, const char *value, char *err, size_t n)
{
    PyStatus st = PyConfig_SetBytesString(config, field, value);
    if (PyStatus_Exception(st)) {
        snprintf(err, n, "Python configuration: %s", st.err_msg ? st.err_msg : "?");
        return -1;
    }
    return 0;
}

static int init_python(const pz_config *cfg, char *err, size_t n)
{
    /* isolated: PYTHONHOME/PYTHONPATH/PATH and the user's site do not matter; UTF-8 mode, and the
       host's locale and signal handlers stay as they are */
    PyPreConfig pre;
    PyPreConfig_InitIsolatedConfig(&pre);
    pre.utf8_mode = 1;
    pre.configure_locale = 0;
    PyStatus st = Py_PreInitialize(&pre);
    if (PyStatus_Exception(st)) {
        snprintf(err, n, "Python pre-initialization failed: %s", st.err_msg ? st.err_msg : "?");
        return -1;
    }
    PyConfig config;
    PyConfig_InitIsolatedConfig(&config);
    config.install_signal_handlers = 0;
    config.parse_argv = 0;
    int rc = 0;
    if (cfg->home[0])
        rc |= set_string(&config, &config.home, cfg->home, err, n);
    if (!rc && cfg->executable[0])
        rc |= set_string(&config, &config.executable, cfg->executable, err, n);
    if (!rc && cfg->paths && cfg->paths[0]) {
        /* the module path the build recorded: stdlib, lib-dynload, the building environment's
           site-packages (numpy, numba, pythonfmu); no site: .pth files are not needed */
        config.site_import = 0;
        config.module_search_paths_set = 1;
        for (const char *p = cfg->paths; *p && !rc;) {
            size_t len = strcspn(p, "\n");
            char entry[PZ_PATH_MAX];
            snprintf(entry, sizeof entry, "%.*s", (int)len, p);
            wchar_t *w = Py_DecodeLocale(entry, NULL);
            if (!w || PyStatus_Exception(PyWideStringList_Append(&config.module_search_paths, w))) {
                snprintf(err, n, "Python configuration: cannot use the module path entry %.900s", entry);
                rc = -1;
            }
            PyMem_RawFree(w);
            p += len + (p[len] == '\n');
        }
    }
    if (rc) {
        PyConfig_Clear(&config);
        return -1;
    }
    st = Py_InitializeFromConfig(&config);
    PyConfig_Clear(&config);
    if (PyStatus_Exception(st)) {
        snprintf(err, n, "starting Python (home %.900s) failed: %s%s%.600s", cfg->home[0] ? cfg->home : "(default)",
                 st.func ? st.func : "", st.func ? ": " : "", st.err_msg ? st.err_msg : "exit requested");
        return -1;
    }
    main_ts = PyEval_SaveThread();   /* this thread keeps the main state; the GIL is free */
    thread_ts = main_ts;
    return 0;
}

static int start(const pz_config *cfg, char *err, size_t n)
{
    pthread_mutex_lock(&start_lock);
    if (started == 0) {
        if (Py_IsInitialized() || init_python(cfg, start_error, sizeof start_error) == 0) {
            /* the host's interpreter (already running) or ours: used, never finalized */
            interp = PyInterpreterState_Main();
            pthread_key_create(&ts_key, thread_ended);
            atexit(at_exit);
            started = 1;
        } else {
            started = -1;   /* a failed start cannot be retried in this process */
        }
    }
    int ok = started == 1 && python_alive();
    if (!ok)
        snprintf(err, n, "%s", started == -1 ? start_error : "the process's Python has been finalized");
    pthread_mutex_unlock(&start_lock);
    return ok ? 0 : -1;
}

/* ---------------------------------------------------------------------------------------------
 * messages
 * ------------------------------------------------------------------------------------------- */

static void logf_(pz_instance *I, fmi2Status status, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void logf_(pz_instance *I, fmi2Status status, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int len = vsnprintf(NULL, 0, fmt, ap);
    va_end(ap);
    char *buf = len >= 0 ? malloc((size_t)len + 1) : NULL;
    if (!buf) {
        I->log(I, status, NULL, "(out of memory for a message)");
        return;
    }
    va_start(ap, fmt);
    vsnprintf(buf, (size_t)len + 1, fmt, ap);
    va_end(ap);
    I->log(I, status, NULL, buf);
    free(buf);
}

/* Log the pending Python exception ("what: Type: message") and clear it. */
static fmi2Status log_exception(pz_instance *I, const char *what)
{
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    const char *tname = type && PyType_Check(type) ? ((PyTypeObject *)type)->tp_name : "error";
    PyObject *text = value ? PyObject_Str(value) : NULL;
    const char *msg = text ? PyUnicode_AsUTF8(text) : NULL;
    if (!msg) {
        PyErr_Clear();
        msg = "(no message)";
    }
    logf_(I, fmi2Error, "%s: %s: %s", what, tname, msg);
    Py_XDECREF(text);
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(tb);
    return fmi2Error;
}

/* Forward the slave's queued messages (pythonfmu's LogMsg: status, category, msg) to the host. */
static void drain(pz_instance *I, pz_py *p)
{
    PyObject *q = p->queue;
    Py_ssize_t n = q ? PyList_GET_SIZE(q) : 0;
    if (n == 0)
        return;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *m = PyList_GET_ITEM(q, i);
        PyObject *st = PyObject_GetAttrString(m, "status");
        PyObject *cat = PyObject_GetAttrString(m, "category");
        PyObject *msg = PyObject_GetAttrString(m, "msg");
        long status = st ? PyLong_AsLong(st) : fmi2Error;
        if (status < fmi2OK || status > fmi2Pending)
            status = fmi2Error;
        const char *category = cat && PyUnicode_Check(cat) ? PyUnicode_AsUTF8(cat) : NULL;
        const char *text = msg && PyUnicode_Check(msg) ? PyUnicode_AsUTF8(msg) : NULL;
        PyErr_Clear();
        I->log(I, (fmi2Status)status, category, text ? text : "(a log message that is not text)");
        Py_XDECREF(st);
        Py_XDECREF(cat);
        Py_XDECREF(msg);
    }
    if (PyList_SetSlice(q, 0, n, NULL) != 0)
        PyErr_Clear();
}

static fmi2Status gone(pz_instance *I, const char *what)
{
    logf_(I, fmi2Fatal, "%s: Python is no longer available in this process (%s)", what,
          exiting ? "the process is exiting" : "the host finalized its interpreter");
    return fmi2Fatal;
}

/* ---------------------------------------------------------------------------------------------
 * calling the slave
 * ------------------------------------------------------------------------------------------- */

/* obj._rt_call(method, *args) with args built from fmt (a tuple format such as "(dO)"); returns
   the status and, if wanted, a new reference to the result. With the GIL held. */
static fmi2Status invoke(pz_instance *I, PyObject **result, const char *method, const char *fmt, ...)
{
    pz_py *p = I->py;
    if (result)
        *result = NULL;
    va_list ap;
    va_start(ap, fmt);
    PyObject *rest = Py_VaBuildValue(fmt, ap);
    va_end(ap);
    PyObject *args = NULL, *r = NULL;
    fmi2Status st = fmi2Error;
    if (!rest || !PyTuple_Check(rest)) {
        st = log_exception(I, method);
        goto out;
    }
    Py_ssize_t n = PyTuple_GET_SIZE(rest);
    args = PyTuple_New(n + 1);
    if (!args) {
        st = log_exception(I, method);
        goto out;
    }
    PyTuple_SET_ITEM(args, 0, PyUnicode_FromString(method));
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *a = PyTuple_GET_ITEM(rest, i);
        Py_INCREF(a);
        PyTuple_SET_ITEM(args, i + 1, a);
    }
    r = PyObject_Call(p->call, args, NULL);
    if (!r) {
        st = log_exception(I, method);
    } else if (!PyTuple_Check(r) || PyTuple_GET_SIZE(r) != 2 || !PyLong_Check(PyTuple_GET_ITEM(r, 0))) {
        logf_(I, fmi2Error, "%s: the slave answered outside the runtime protocol", method);
    } else {
        long s = PyLong_AsLong(PyTuple_GET_ITEM(r, 0));
        st = s >= fmi2OK && s <= fmi2Fatal ? (fmi2Status)s : fmi2Error;
        if (result && st <= fmi2Warning) {
            *result = PyTuple_GET_ITEM(r, 1);
            Py_INCREF(*result);
        }
    }
out:
    Py_XDECREF(rest);
    Py_XDECREF(args);
    Py_XDECREF(r);
    drain(I, p);
    return st;
}

static void release_buffers(pz_py *p)
{
    if (p->io.obj)
        PyBuffer_Release(&p->io);
    if (p->ctl.obj)
        PyBuffer_Release(&p->ctl);
}

static int view(pz_instance *I, PyObject *array, Py_buffer *b, int writable, const char *format,
                Py_ssize_t itemsize, const char *what)
{
    int flags = PyBUF_FORMAT | PyBUF_ND | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(array, b, flags) != 0)
        return log_exception(I, what), -1;
    if (b->ndim != 1 || b->itemsize != itemsize || !b->format || strcmp(b->format, format) != 0) {
        logf_(I, fmi2Error, "%s: not a one-dimensional array of '%s'", what, format);
        PyBuffer_Release(b);
        return -1;
    }
    return 0;
}

/* Make a slave object and bind its shared arrays (protocol PZ_PROTOCOL); on success the
   instance's fast path and p->obj/step/call/queue/io/ctl describe the new object. */
static int make_slave(pz_instance *I, pz_py *p)
{
    PyObject *kw = Py_BuildValue("{s:s,s:s,s:O}", "instance_name", I->name, "resources", p->resources,
                                 "visible", p->visible ? Py_True : Py_False);
    PyObject *noargs = PyTuple_New(0);
    PyObject *obj = kw && noargs ? PyObject_Call(p->cls, noargs, kw) : NULL;
    Py_XDECREF(kw);
    Py_XDECREF(noargs);
    if (!obj)
        return log_exception(I, "creating the slave"), -1;
    PyObject *bound = PyObject_CallMethod(obj, "_rt_bind", "i", PZ_PROTOCOL);
    PyObject *values, *ctl, *slots, *step = NULL, *call = NULL, *queue = NULL;
    Py_buffer io = {0}, cb = {0}, sb = {0};
    int32_t *slot = NULL;
    long n_in = 0;
    if (!bound || !PyArg_ParseTuple(bound, "OOOl", &values, &ctl, &slots, &n_in)) {
        log_exception(I, "binding the slave");
        goto fail;
    }
    if (view(I, values, &io, 1, "d", sizeof(double), "the slave's values") ||
        view(I, ctl, &cb, 0, "i", sizeof(int32_t), "the slave's control") ||
        view(I, slots, &sb, 0, "i", sizeof(int32_t), "the slave's value references"))
        goto fail;
    Py_ssize_t n_io = io.shape[0];
    if (sb.shape[0] != n_io || cb.shape[0] < 2 || n_in < 0 || n_in > n_io) {
        logf_(I, fmi2Error, "binding the slave: inconsistent shared arrays");
        goto fail;
    }
    const int32_t *vrs = sb.buf;
    uint32_t n_slot = 0;
    for (Py_ssize_t k = 0; k < n_io; k++)
        if (vrs[k] >= 0 && (uint32_t)vrs[k] + 1 > n_slot)
            n_slot = (uint32_t)vrs[k] + 1;
    slot = malloc((n_slot ? n_slot : 1) * sizeof *slot);
    step = PyObject_GetAttrString(obj, "_rt_do_step");
    call = PyObject_GetAttrString(obj, "_rt_call");
    queue = PyObject_GetAttrString(obj, "log_queue");
    if (!slot || !step || !call || !queue || !PyList_Check(queue)) {
        if (PyErr_Occurred())
            log_exception(I, "binding the slave");
        else
            logf_(I, fmi2Error, "binding the slave: out of memory or no log queue");
        goto fail;
    }
    for (uint32_t v = 0; v < n_slot; v++)
        slot[v] = -1;
    for (Py_ssize_t k = 0; k < n_io; k++)
        if (vrs[k] >= 0)
            slot[vrs[k]] = (int32_t)k;
    PyBuffer_Release(&sb);
    Py_DECREF(bound);
    /* swap in (fmi2Reset replaces a working object only when the new one is complete) */
    release_buffers(p);
    Py_XDECREF(p->obj);
    Py_XDECREF(p->step);
    Py_XDECREF(p->call);
    Py_XDECREF(p->queue);
    free(I->slot);
    p->obj = obj;
    p->step = step;
    p->call = call;
    p->queue = queue;
    p->io = io;
    p->ctl = cb;
    I->io = io.buf;
    I->ctl = cb.buf;
    I->n_in = (int)n_in;
    I->n_io = (int)n_io;
    I->slot = slot;
    I->n_slot = n_slot;
    drain(I, p);
    return 0;
fail:
    if (io.obj)
        PyBuffer_Release(&io);
    if (cb.obj)
        PyBuffer_Release(&cb);
    if (sb.obj)
        PyBuffer_Release(&sb);
    free(slot);
    Py_XDECREF(step);
    Py_XDECREF(call);
    /* what the failed object logged (queue may be unset: read it from the object) */
    if (!queue)
        queue = PyObject_GetAttrString(obj, "log_queue");
    PyErr_Clear();
    if (queue && PyList_Check(queue)) {
        PyObject *keep = p->queue;
        p->queue = queue;
        drain(I, p);
        p->queue = keep;
    }
    Py_XDECREF(queue);
    Py_XDECREF(bound);
    Py_DECREF(obj);
    return -1;
}

static fmi2Status instantiate(pz_instance *I, const pz_config *cfg, int visible)
{
    pz_gil g;
    if (enter(&g) != 0)
        return gone(I, "fmi2Instantiate");
    fmi2Status st = fmi2Error;
    pz_py *p = calloc(1, sizeof *p);
    if (!p || !(p->resources = strdup(cfg->resources))) {
        logf_(I, fmi2Error, "fmi2Instantiate: out of memory");
        free(p);
        leave(&g);
        return fmi2Error;
    }
    p->visible = visible;
    I->py = p;
    /* the slave script and its bundle are modules in resources/ (unique names per FMU build) */
    PyObject *sys_path = PySys_GetObject("path");   /* borrowed */
    PyObject *dir = PyUnicode_DecodeFSDefault(cfg->resources);
    if (!sys_path || !PyList_Check(sys_path) || !dir) {
        log_exception(I, "fmi2Instantiate: sys.path");
        Py_XDECREF(dir);
        goto out;
    }
    int has = PySequence_Contains(sys_path, dir);
    if (has == 0)
        has = PyList_Insert(sys_path, 0, dir) == 0;
    Py_DECREF(dir);
    if (has < 0) {
        log_exception(I, "fmi2Instantiate: sys.path");
        goto out;
    }
    PyObject *module = PyImport_ImportModule(cfg->module);
    if (!module) {
        PyObject *type, *value, *tb;
        PyErr_Fetch(&type, &value, &tb);
        PyObject *where = PySys_GetObject("path");
        PyObject *text = where ? PyObject_Str(where) : NULL;
        const char *path = text ? PyUnicode_AsUTF8(text) : NULL;
        if (!path)
            path = "?";
        PyErr_Restore(type, value, tb);
        char what[PZ_PATH_MAX + 512];
        snprintf(what, sizeof what, "fmi2Instantiate: importing the slave module %s (Python %.6s, module path %.3000s)",
                 cfg->module, Py_GetVersion(), path);
        log_exception(I, what);
        Py_XDECREF(text);
        PyErr_Clear();
        goto out;
    }
    p->cls = PyObject_GetAttrString(module, cfg->cls);
    Py_DECREF(module);
    if (!p->cls) {
        log_exception(I, "fmi2Instantiate: the slave class");
        goto out;
    }
    if (make_slave(I, p) == 0)
        st = fmi2OK;
out:
    if (st != fmi2OK) {
        Py_XDECREF(p->cls);
        free(p->resources);
        free(p);
        I->py = NULL;
    }
    leave(&g);
    return st;
}

static void free_strings(pz_py *p)
{
    for (size_t k = 0; k < p->n_strings; k++)
        free(p->strings[k]);
    free(p->strings);
    p->strings = NULL;
    p->n_strings = 0;
}

static void free_instance(pz_instance *I)
{
    pz_py *p = I->py;
    if (!p)
        return;
    pz_gil g;
    int alive = enter(&g) == 0;
    for (pz_state *s = p->states, *next; s; s = next) {
        next = s->next;
        if (alive) {
            Py_XDECREF(s->obj);
            Py_XDECREF(s->bytes);
        }
        s->magic = 0;
        free(s);
    }
    if (alive) {
        /* the views first: then the arrays can go with the slave */
        release_buffers(p);
        Py_XDECREF(p->step);
        Py_XDECREF(p->call);
        Py_XDECREF(p->queue);
        Py_XDECREF(p->obj);
        Py_XDECREF(p->cls);
        leave(&g);
    }
    /* without Python (exit, or the host finalized it) its objects are left as they are */
    I->io = NULL;
    I->ctl = NULL;
    free(I->slot);
    I->slot = NULL;
    I->n_slot = 0;
    free_strings(p);
    free(p->resources);
    free(p);
    I->py = NULL;
}

/* ---------------------------------------------------------------------------------------------
 * the FMI functions that enter Python
 * ------------------------------------------------------------------------------------------- */

#define ENTER(what)                                                                                \
    pz_gil g;                                                                                      \
    if (enter(&g) != 0)                                                                            \
        return gone(I, what)

static fmi2Status call(pz_instance *I, const char *method)
{
    pz_gil g;
    if (enter(&g) != 0) {
        if (strcmp(method, "terminate") == 0) {
            /* a host tearing down at exit (or after finalizing its Python): nothing left to do */
            logf_(I, fmi2OK, "terminate: Python is no longer available; nothing to terminate");
            return fmi2OK;
        }
        return gone(I, method);
    }
    fmi2Status st = invoke(I, NULL, method, "()");
    leave(&g);
    return st;
}

static fmi2Status setup(pz_instance *I, int tol_defined, double tol, double start_time, int stop_defined,
                        double stop)
{
    ENTER("fmi2SetupExperiment");
    PyObject *py_stop = stop_defined ? PyFloat_FromDouble(stop) : (Py_INCREF(Py_None), Py_None);
    PyObject *py_tol = tol_defined ? PyFloat_FromDouble(tol) : (Py_INCREF(Py_None), Py_None);
    fmi2Status st = py_stop && py_tol ? invoke(I, NULL, "setup_experiment", "(dOO)", start_time, py_stop, py_tol)
                                      : log_exception(I, "fmi2SetupExperiment");
    Py_XDECREF(py_stop);
    Py_XDECREF(py_tol);
    leave(&g);
    return st;
}

static fmi2Status reset(pz_instance *I)
{
    ENTER("fmi2Reset");
    fmi2Status st = make_slave(I, I->py) == 0 ? fmi2OK : fmi2Error;
    leave(&g);
    return st;
}

static fmi2Status do_step(pz_instance *I, double t, double h)
{
    ENTER("fmi2DoStep");
    pz_py *p = I->py;
    fmi2Status st;
    PyObject *args[3] = {NULL, PyFloat_FromDouble(t), PyFloat_FromDouble(h)};
    PyObject *r = args[1] && args[2]
                      ? PyObject_Vectorcall(p->step, args + 1, 2 | PY_VECTORCALL_ARGUMENTS_OFFSET, NULL)
                      : NULL;
    Py_XDECREF(args[1]);
    Py_XDECREF(args[2]);
    if (!r) {
        st = log_exception(I, "fmi2DoStep");
    } else {
        long s = PyLong_Check(r) ? PyLong_AsLong(r) : -1;
        st = s >= fmi2OK && s <= fmi2Fatal ? (fmi2Status)s : fmi2Error;
        Py_DECREF(r);
    }
    drain(I, p);
    leave(&g);
    return st;
}

static const char *const SETTERS[] = {"set_real", "set_integer", "set_boolean", "set_string"};
static const char *const GETTERS[] = {"get_real", "get_integer", "get_boolean", "get_string"};

static PyObject *vr_list(const fmi2ValueReference *vr, size_t n)
{
    PyObject *l = PyList_New((Py_ssize_t)n);
    for (size_t k = 0; l && k < n; k++) {
        PyObject *x = PyLong_FromUnsignedLong(vr[k]);
        if (!x) {
            Py_CLEAR(l);
            break;
        }
        PyList_SET_ITEM(l, (Py_ssize_t)k, x);
    }
    return l;
}

static fmi2Status set_values(pz_instance *I, int type, const fmi2ValueReference *vr, size_t n, const void *values)
{
    ENTER(SETTERS[type]);
    fmi2Status st;
    PyObject *vrs = vr_list(vr, n), *vals = PyList_New((Py_ssize_t)n);
    for (size_t k = 0; vrs && vals && k < n; k++) {
        PyObject *x = type == PZ_REAL      ? PyFloat_FromDouble(((const fmi2Real *)values)[k])
                      : type == PZ_INTEGER ? PyLong_FromLong(((const fmi2Integer *)values)[k])
                      : type == PZ_BOOLEAN ? PyBool_FromLong(((const fmi2Boolean *)values)[k] != fmi2False)
                                           : PyUnicode_FromString(((const fmi2String *)values)[k]);
        if (!x) {
            Py_CLEAR(vals);
            break;
        }
        PyList_SET_ITEM(vals, (Py_ssize_t)k, x);
    }
    if (vrs && vals)
        st = invoke(I, NULL, SETTERS[type], "(OO)", vrs, vals);
    else
        st = log_exception(I, SETTERS[type]);
    Py_XDECREF(vrs);
    Py_XDECREF(vals);
    leave(&g);
    return st;
}

static fmi2Status get_values(pz_instance *I, int type, const fmi2ValueReference *vr, size_t n, void *values)
{
    ENTER(GETTERS[type]);
    pz_py *p = I->py;
    PyObject *vrs = vr_list(vr, n), *res = NULL;
    fmi2Status st = vrs ? invoke(I, &res, GETTERS[type], "(O)", vrs) : log_exception(I, GETTERS[type]);
    Py_XDECREF(vrs);
    if (st <= fmi2Warning) {
        PyObject *seq = res ? PySequence_Fast(res, "not a sequence") : NULL;
        if (!seq || (size_t)PySequence_Fast_GET_SIZE(seq) != n) {
            PyErr_Clear();
            logf_(I, fmi2Error, "%s: the slave returned %s values for %zu value references", GETTERS[type],
                  seq ? "a different number of" : "no", n);
            st = fmi2Error;
        } else {
            if (type == PZ_STRING)
                free_strings(p);
            if (type == PZ_STRING && !(p->strings = calloc(n, sizeof *p->strings)))
                st = fmi2Error;
            for (size_t k = 0; k < n && st <= fmi2Warning; k++) {
                PyObject *x = PySequence_Fast_GET_ITEM(seq, (Py_ssize_t)k);
                if (type == PZ_REAL) {
                    ((fmi2Real *)values)[k] = PyFloat_AsDouble(x);
                } else if (type == PZ_INTEGER) {
                    long v = PyLong_AsLong(x);
                    if (v < INT32_MIN || v > INT32_MAX) {
                        logf_(I, fmi2Error, "%s: value %ld of vr %u does not fit an fmi2Integer", GETTERS[type],
                              v, vr[k]);
                        st = fmi2Error;
                    }
                    ((fmi2Integer *)values)[k] = (fmi2Integer)v;
                } else if (type == PZ_BOOLEAN) {
                    int v = PyObject_IsTrue(x);
                    ((fmi2Boolean *)values)[k] = v > 0 ? fmi2True : fmi2False;
                } else {
                    const char *s = PyUnicode_Check(x) ? PyUnicode_AsUTF8(x) : NULL;
                    p->strings[k] = strdup(s ? s : "");
                    p->n_strings = k + 1;
                    ((fmi2String *)values)[k] = p->strings[k];
                }
                if (PyErr_Occurred())
                    st = log_exception(I, GETTERS[type]);
            }
        }
        Py_XDECREF(seq);
    }
    Py_XDECREF(res);
    leave(&g);
    return st;
}

/* ---------------------------------------------------------------------------------------------
 * FMU states
 * ------------------------------------------------------------------------------------------- */

static pz_state *state_of(pz_instance *I, fmi2FMUstate handle, const char *fn)
{
    pz_state *s = handle;
    if (!s || s->magic != PZ_STATE_MAGIC) {
        logf_(I, fmi2Error, "%s: not an FMU state of this FMU (or one already freed)", fn);
        return NULL;
    }
    return s;
}

static fmi2Status keep_state(pz_instance *I, PyObject *obj, fmi2FMUstate *handle)
{
    pz_py *p = I->py;
    pz_state *s = calloc(1, sizeof *s);
    if (!s) {
        Py_DECREF(obj);
        logf_(I, fmi2Error, "out of memory for an FMU state");
        return fmi2Error;
    }
    s->magic = PZ_STATE_MAGIC;
    s->obj = obj;
    s->owner = I;
    s->next = p->states;
    p->states = s;
    *handle = s;
    return fmi2OK;
}

static fmi2Status get_state(pz_instance *I, fmi2FMUstate *handle)
{
    ENTER("fmi2GetFMUstate");
    PyObject *obj;
    fmi2Status st = invoke(I, &obj, "_get_fmu_state", "()");
    if (st <= fmi2Warning) {
        if (*handle) {   /* a state of ours, not freed since: overwritten in place */
            pz_state *s = state_of(I, *handle, "fmi2GetFMUstate");
            if (s) {
                Py_XDECREF(s->obj);
                Py_CLEAR(s->bytes);
                s->obj = obj;
            } else {
                Py_DECREF(obj);
                st = fmi2Error;
            }
        } else {
            fmi2Status k = keep_state(I, obj, handle);
            st = k > st ? k : st;
        }
    }
    leave(&g);
    return st;
}

static fmi2Status set_state(pz_instance *I, fmi2FMUstate handle)
{
    ENTER("fmi2SetFMUstate");
    pz_state *s = state_of(I, handle, "fmi2SetFMUstate");
    fmi2Status st = s ? invoke(I, NULL, "_set_fmu_state", "(O)", s->obj) : fmi2Error;
    leave(&g);
    return st;
}

static fmi2Status free_state(pz_instance *I, fmi2FMUstate *handle)
{
    ENTER("fmi2FreeFMUstate");
    pz_state *s = state_of(I, *handle, "fmi2FreeFMUstate");
    if (!s) {
        leave(&g);
        return fmi2Error;
    }
    pz_py *owner = s->owner->py;
    for (pz_state **link = owner ? &owner->states : NULL; link && *link; link = &(*link)->next)
        if (*link == s) {
            *link = s->next;
            break;
        }
    Py_XDECREF(s->obj);
    Py_XDECREF(s->bytes);
    s->magic = 0;
    free(s);
    *handle = NULL;
    leave(&g);
    return fmi2OK;
}

static fmi2Status serialized(pz_instance *I, pz_state *s)
{
    if (s->bytes)
        return fmi2OK;
    PyObject *b;
    fmi2Status st = invoke(I, &b, "_rt_serialize", "(O)", s->obj);
    if (st <= fmi2Warning) {
        if (!PyBytes_Check(b)) {
            logf_(I, fmi2Error, "fmi2SerializeFMUstate: the slave did not return bytes");
            Py_DECREF(b);
            return fmi2Error;
        }
        s->bytes = b;
    }
    return st;
}

static fmi2Status serialized_size(pz_instance *I, fmi2FMUstate handle, size_t *size)
{
    ENTER("fmi2SerializedFMUstateSize");
    pz_state *s = state_of(I, handle, "fmi2SerializedFMUstateSize");
    fmi2Status st = s ? serialized(I, s) : fmi2Error;
    if (st <= fmi2Warning)
        *size = (size_t)PyBytes_GET_SIZE(s->bytes);
    leave(&g);
    return st;
}

static fmi2Status serialize(pz_instance *I, fmi2FMUstate handle, fmi2Byte *bytes, size_t size)
{
    ENTER("fmi2SerializeFMUstate");
    pz_state *s = state_of(I, handle, "fmi2SerializeFMUstate");
    fmi2Status st = s ? serialized(I, s) : fmi2Error;
    if (st <= fmi2Warning) {
        size_t need = (size_t)PyBytes_GET_SIZE(s->bytes);
        if (size < need) {
            logf_(I, fmi2Error, "fmi2SerializeFMUstate: the buffer has %zu bytes, the state needs %zu (from "
                  "fmi2SerializedFMUstateSize)", size, need);
            st = fmi2Error;
        } else {
            memcpy(bytes, PyBytes_AS_STRING(s->bytes), need);
            Py_CLEAR(s->bytes);
        }
    }
    leave(&g);
    return st;
}

static fmi2Status deserialize(pz_instance *I, const fmi2Byte *bytes, size_t size, fmi2FMUstate *handle)
{
    ENTER("fmi2DeSerializeFMUstate");
    PyObject *obj;
    /* never fails for bad bytes: the slave returns an invalid-state marker that fmi2SetFMUstate refuses */
    fmi2Status st = invoke(I, &obj, "_fmu_state_from_bytes", "(y#)", bytes, (Py_ssize_t)size);
    if (st <= fmi2Warning) {
        fmi2Status k = keep_state(I, obj, handle);
        st = k > st ? k : st;
    }
    leave(&g);
    return st;
}

__attribute__((visibility("default"))) const pz_bridge piezo_fmu_bridge_1 = {
    PZ_PROTOCOL, start,        instantiate, free_instance,   call,      setup,     reset,       do_step,
    set_values,  get_values,   get_state,   set_state,       free_state, serialized_size, serialize,
    deserialize,
};
