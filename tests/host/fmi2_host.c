/* A minimal FMI 2.0 co-simulation host in C, for tests/test_runtime.py (compiled during the test run).
 *
 * It loads extracted FMUs with dlopen and the standard's function names, like any C host (no
 * Python anywhere unless --preload loads a libpython first). Every command prints its results as
 * lines "key value..." with doubles in C99 hex ("%a", exact), and a final "status ok" line; any
 * failing FMI call prints "fail <function> <status>" and exits 3.
 *
 *   fmi2_host [--preload LIBPYTHON] [--int MODELID:VR=VALUE]... COMMAND ARGS...
 *
 *   run FMU START STOP STEP OUT_VRS [IN_VR WAVE]      one instance, fixed steps; outputs after
 *                                                      initialization and after every step; with
 *                                                      IN_VR the input follows wave WAVE (below)
 *   churn FMU N                                        N times instantiate, 3 steps, free
 *   threads FMU STEP N OUT_VRS IN_VR WAVE              two instances, each stepped on its own thread
 *   nan FMU IN_VR OUT_VRS                              NaN input: its status, then a good input and a step
 *   loop ACT SEN COM STOP STEP                         the closed loop, Gauss-Seidel (piezo_fmu.cosim's order)
 *   bench FMU N                                        us per fmi2DoStep (+ set/get) on this thread and on another
 *   bench-loop ACT SEN COM N STEP                      us per communication step of the closed loop
 *   orders ACT SEN COM                                 instances of three FMUs freed and libraries closed
 *                                                      in mixed orders, one reopened; exits with some alive
 *
 * --preload loads a Python library (RTLD_GLOBAL, not started) before any FMU: a host that brought
 * its own. --int sets an Integer (e.g. simulation.engine) of every instance of that FMU before
 * initialization.
 * FMU is "DIR:MODELIDENTIFIER:GUID" of an extracted FMU; OUT_VRS is a comma-separated list of
 * value references. WAVE 1: 6 + 6 sin(2 pi 40 t) + 2 sin(2 pi 230 t), WAVE 2: 300 (1 + sin(2 pi 25 t)).
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

/* FMI 2.0 types as the standard defines them (section 2.1.2) */
typedef void *fmi2Component;
typedef unsigned int fmi2ValueReference;
typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef struct {
    void (*logger)(void *, const char *, fmi2Status, const char *, const char *, ...);
    void *(*allocateMemory)(size_t, size_t);
    void (*freeMemory)(void *);
    void (*stepFinished)(void *, fmi2Status);
    void *componentEnvironment;
} fmi2CallbackFunctions;

typedef struct {
    char dir[2048], id[256], guid[128], uri[2200];
    void *lib;
    fmi2Component (*instantiate)(const char *, int, const char *, const char *, const fmi2CallbackFunctions *,
                                 int, int);
    void (*free_instance)(fmi2Component);
    fmi2Status (*setup)(fmi2Component, int, double, double, int, double);
    fmi2Status (*enter)(fmi2Component);
    fmi2Status (*exit_init)(fmi2Component);
    fmi2Status (*terminate)(fmi2Component);
    fmi2Status (*set_real)(fmi2Component, const fmi2ValueReference *, size_t, const double *);
    fmi2Status (*set_integer)(fmi2Component, const fmi2ValueReference *, size_t, const int *);
    fmi2Status (*get_real)(fmi2Component, const fmi2ValueReference *, size_t, double *);
    fmi2Status (*do_step)(fmi2Component, double, double, int);
} fmu_t;

static int n_errors;   /* messages logged with fmi2Error or worse */
static struct {
    char id[256];
    fmi2ValueReference vr;
    int value;
} ints[8];             /* --int */
static int n_ints;

static void logger(void *env, const char *name, fmi2Status status, const char *category, const char *message, ...)
{
    (void)env;
    char text[4096];
    va_list ap;
    va_start(ap, message);
    vsnprintf(text, sizeof text, message, ap);
    va_end(ap);
    if (status >= fmi2Error)
        __atomic_add_fetch(&n_errors, 1, __ATOMIC_SEQ_CST);
    fprintf(stderr, "[%s] status %d %s: %s\n", name, (int)status, category ? category : "-", text);
}

static const fmi2CallbackFunctions CALLBACKS = {logger, calloc, free, NULL, NULL};

static void *sym(fmu_t *f, const char *name)
{
    void *p = dlsym(f->lib, name);
    if (!p) {
        printf("fail dlsym %s\n", name);
        exit(3);
    }
    return p;
}

static void load(fmu_t *f, const char *spec)
{
    char buf[4096];
    snprintf(buf, sizeof buf, "%s", spec);
    char *a = strtok(buf, ":"), *b = strtok(NULL, ":"), *c = strtok(NULL, "");
    if (!a || !b || !c) {
        printf("fail spec %s\n", spec);
        exit(2);
    }
    snprintf(f->dir, sizeof f->dir, "%s", a);
    snprintf(f->id, sizeof f->id, "%s", b);
    snprintf(f->guid, sizeof f->guid, "%s", c);
    snprintf(f->uri, sizeof f->uri, "file://%s/resources", f->dir);
    char path[2600];
    snprintf(path, sizeof path, "%s/binaries/linux64/%s.so", f->dir, f->id);
    f->lib = dlopen(path, RTLD_NOW | RTLD_LOCAL);   /* what most hosts do */
    if (!f->lib) {
        printf("fail dlopen %s\n", dlerror());
        exit(3);
    }
    *(void **)&f->instantiate = sym(f, "fmi2Instantiate");
    *(void **)&f->free_instance = sym(f, "fmi2FreeInstance");
    *(void **)&f->setup = sym(f, "fmi2SetupExperiment");
    *(void **)&f->enter = sym(f, "fmi2EnterInitializationMode");
    *(void **)&f->exit_init = sym(f, "fmi2ExitInitializationMode");
    *(void **)&f->terminate = sym(f, "fmi2Terminate");
    *(void **)&f->set_real = sym(f, "fmi2SetReal");
    *(void **)&f->set_integer = sym(f, "fmi2SetInteger");
    *(void **)&f->get_real = sym(f, "fmi2GetReal");
    *(void **)&f->do_step = sym(f, "fmi2DoStep");
}

static void check(fmi2Status st, const char *what)
{
    if (st > fmi2Warning) {
        printf("fail %s %d\n", what, (int)st);
        exit(3);
    }
}

static fmi2Component instantiate(fmu_t *f, const char *name)
{
    fmi2Component c = f->instantiate(name, 1, f->guid, f->uri, &CALLBACKS, 0, 0);
    if (!c) {
        printf("fail fmi2Instantiate NULL\n");
        exit(3);
    }
    for (int i = 0; i < n_ints; i++)
        if (strcmp(ints[i].id, f->id) == 0)
            check(f->set_integer(c, &ints[i].vr, 1, &ints[i].value), "fmi2SetInteger");
    return c;
}

static fmi2Component make(fmu_t *f, const char *name, double start, double stop)
{
    fmi2Component c = instantiate(f, name);
    check(f->setup(c, 0, 0.0, start, 1, stop), "fmi2SetupExperiment");
    check(f->enter(c), "fmi2EnterInitializationMode");
    check(f->exit_init(c), "fmi2ExitInitializationMode");
    return c;
}

static size_t parse_vrs(const char *s, fmi2ValueReference *vr, size_t max)
{
    size_t n = 0;
    char buf[1024];
    snprintf(buf, sizeof buf, "%s", s);
    for (char *t = strtok(buf, ","); t && n < max; t = strtok(NULL, ","))
        vr[n++] = (fmi2ValueReference)strtoul(t, NULL, 10);
    return n;
}

static double wave(int kind, double t)
{
    if (kind == 1)
        return 6.0 + 6.0 * sin(2 * M_PI * 40.0 * t) + 2.0 * sin(2 * M_PI * 230.0 * t);
    return 300.0 * (1.0 + sin(2 * M_PI * 25.0 * t));
}

static void print_row(const char *key, double t, const double *v, size_t n)
{
    printf("%s %a", key, t);
    for (size_t k = 0; k < n; k++)
        printf(" %a", v[k]);
    printf("\n");
}

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

/* -- run ---------------------------------------------------------------------------------------- */

static int cmd_run(int argc, char **argv)
{
    if (argc < 5)
        return 2;
    fmu_t f;
    load(&f, argv[0]);
    double start = atof(argv[1]), stop = atof(argv[2]), h = atof(argv[3]);
    fmi2ValueReference out[16], in = 0;
    size_t n_out = parse_vrs(argv[4], out, 16);
    int kind = 0;
    if (argc >= 7) {
        in = (fmi2ValueReference)atoi(argv[5]);
        kind = atoi(argv[6]);
    }
    fmi2Component c = make(&f, "run", start, stop);
    double v[16];
    check(f.get_real(c, out, n_out, v), "fmi2GetReal");
    print_row("row", start, v, n_out);
    long n = lround((stop - start) / h);
    for (long k = 0; k < n; k++) {
        double t = start + k * h;
        if (kind) {
            double u = wave(kind, t);
            check(f.set_real(c, &in, 1, &u), "fmi2SetReal");
        }
        check(f.do_step(c, t, h, 1), "fmi2DoStep");
        check(f.get_real(c, out, n_out, v), "fmi2GetReal");
        print_row("row", start + (k + 1) * h, v, n_out);
    }
    check(f.terminate(c), "fmi2Terminate");
    f.free_instance(c);
    dlclose(f.lib);
    return 0;
}

/* -- churn -------------------------------------------------------------------------------------- */

static int cmd_churn(int argc, char **argv)
{
    if (argc < 2)
        return 2;
    fmu_t f;
    load(&f, argv[0]);
    int n = atoi(argv[1]);
    for (int i = 0; i < n; i++) {
        char name[32];
        snprintf(name, sizeof name, "churn%d", i);
        fmi2Component c = make(&f, name, 0.0, 1.0);
        for (int k = 0; k < 3; k++)
            check(f.do_step(c, k * 1e-4, 1e-4, 1), "fmi2DoStep");
        check(f.terminate(c), "fmi2Terminate");
        f.free_instance(c);
    }
    printf("churned %d\n", n);
    return 0;
}

/* -- threads ------------------------------------------------------------------------------------ */

typedef struct {
    fmu_t *f;
    fmi2Component c;
    double h;
    long n;
    fmi2ValueReference out[16], in;
    size_t n_out;
    int kind;
    double *rows;
} job_t;

static void *stepper(void *arg)
{
    job_t *j = arg;
    for (long k = 0; k < j->n; k++) {
        double t = k * j->h, u = wave(j->kind, t);
        check(j->f->set_real(j->c, &j->in, 1, &u), "fmi2SetReal");
        check(j->f->do_step(j->c, t, j->h, 1), "fmi2DoStep");
        check(j->f->get_real(j->c, j->out, j->n_out, j->rows + k * j->n_out), "fmi2GetReal");
    }
    return NULL;
}

static int cmd_threads(int argc, char **argv)
{
    if (argc < 6)
        return 2;
    fmu_t f;
    load(&f, argv[0]);
    job_t jobs[2];
    for (int i = 0; i < 2; i++) {
        job_t *j = &jobs[i];
        j->f = &f;
        j->h = atof(argv[1]);
        j->n = atol(argv[2]);
        j->n_out = parse_vrs(argv[3], j->out, 16);
        j->in = (fmi2ValueReference)atoi(argv[4]);
        j->kind = atoi(argv[5]);
        j->rows = calloc((size_t)j->n * j->n_out, sizeof(double));
        j->c = make(&f, i ? "thread1" : "thread0", 0.0, j->n * j->h);
    }
    pthread_t th[2];
    for (int i = 0; i < 2; i++)
        pthread_create(&th[i], NULL, stepper, &jobs[i]);
    for (int i = 0; i < 2; i++)
        pthread_join(th[i], NULL);
    for (int i = 0; i < 2; i++) {
        for (long k = 0; k < jobs[i].n; k++)
            print_row(i ? "row1" : "row0", (k + 1) * jobs[i].h, jobs[i].rows + k * jobs[i].n_out, jobs[i].n_out);
        f.free_instance(jobs[i].c);
        free(jobs[i].rows);
    }
    return 0;
}

/* -- nan ---------------------------------------------------------------------------------------- */

static int cmd_nan(int argc, char **argv)
{
    if (argc < 3)
        return 2;
    fmu_t f;
    load(&f, argv[0]);
    fmi2ValueReference in = (fmi2ValueReference)atoi(argv[1]), out[16];
    size_t n_out = parse_vrs(argv[2], out, 16);
    fmi2Component c = make(&f, "nan", 0.0, 1.0);
    double bad = NAN, good = 1.0, v[16];
    int errors0 = n_errors;
    fmi2Status s_nan = f.set_real(c, &in, 1, &bad);
    int logged = n_errors - errors0;
    fmi2Status s_good = f.set_real(c, &in, 1, &good);
    fmi2Status s_step = f.do_step(c, 0.0, 1e-4, 1);
    fmi2Status s_get = f.get_real(c, out, n_out, v);
    printf("nan %d logged %d good %d step %d get %d\n", (int)s_nan, logged, (int)s_good, (int)s_step, (int)s_get);
    print_row("row", 1e-4, v, n_out);
    f.free_instance(c);
    return 0;
}

/* -- the closed loop ---------------------------------------------------------------------------- */

/* value references: looked up by the test and passed in this order (piezo_fmu.connections) */
typedef struct {
    fmu_t act, sen, com;
    fmi2Component a, s, c;
    fmi2ValueReference a_uc, a_out[3], s_F, s_us, c_us, c_out[2];
    double a_v[3], s_v, c_v[2];
} loop_t;

static void loop_init(loop_t *L, char **argv, double stop)
{
    load(&L->act, argv[0]);
    load(&L->sen, argv[1]);
    load(&L->com, argv[2]);
    /* vr order: Actuator uc x F ua, Sensor F us, Compensator us uc x_target */
    const char *env = getenv("HOST_LOOP_VRS");
    unsigned v[9];
    if (!env || sscanf(env, "%u,%u,%u,%u,%u,%u,%u,%u,%u", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7],
                       &v[8]) != 9) {
        printf("fail HOST_LOOP_VRS\n");
        exit(2);
    }
    L->a_uc = v[0], L->a_out[0] = v[1], L->a_out[1] = v[2], L->a_out[2] = v[3];
    L->s_F = v[4], L->s_us = v[5], L->c_us = v[6], L->c_out[0] = v[7], L->c_out[1] = v[8];
    fmu_t *fs[3] = {&L->act, &L->sen, &L->com};
    fmi2Component *cs[3] = {&L->a, &L->s, &L->c};
    const char *names[3] = {"Actuator", "Sensor", "Compensator"};
    for (int i = 0; i < 3; i++) {
        *cs[i] = instantiate(fs[i], names[i]);
        check(fs[i]->setup(*cs[i], 0, 0.0, 0.0, 1, stop), "fmi2SetupExperiment");
        check(fs[i]->enter(*cs[i]), "fmi2EnterInitializationMode");
    }
    /* initialization in Gauss-Seidel order, inputs from the outputs already known */
    check(L->act.exit_init(L->a), "fmi2ExitInitializationMode");
    check(L->act.get_real(L->a, L->a_out, 3, L->a_v), "fmi2GetReal");
    check(L->sen.set_real(L->s, &L->s_F, 1, &L->a_v[1]), "fmi2SetReal");
    check(L->sen.exit_init(L->s), "fmi2ExitInitializationMode");
    check(L->sen.get_real(L->s, &L->s_us, 1, &L->s_v), "fmi2GetReal");
    check(L->com.set_real(L->c, &L->c_us, 1, &L->s_v), "fmi2SetReal");
    check(L->com.exit_init(L->c), "fmi2ExitInitializationMode");
    check(L->com.get_real(L->c, L->c_out, 2, L->c_v), "fmi2GetReal");
}

static void loop_step(loop_t *L, double t, double h)
{
    check(L->act.set_real(L->a, &L->a_uc, 1, &L->c_v[0]), "fmi2SetReal");
    check(L->act.do_step(L->a, t, h, 1), "fmi2DoStep");
    check(L->act.get_real(L->a, L->a_out, 3, L->a_v), "fmi2GetReal");
    check(L->sen.set_real(L->s, &L->s_F, 1, &L->a_v[1]), "fmi2SetReal");
    check(L->sen.do_step(L->s, t, h, 1), "fmi2DoStep");
    check(L->sen.get_real(L->s, &L->s_us, 1, &L->s_v), "fmi2GetReal");
    check(L->com.set_real(L->c, &L->c_us, 1, &L->s_v), "fmi2SetReal");
    check(L->com.do_step(L->c, t, h, 1), "fmi2DoStep");
    check(L->com.get_real(L->c, L->c_out, 2, L->c_v), "fmi2GetReal");
}

static void loop_print(loop_t *L, double t)
{
    double row[6] = {L->a_v[0], L->a_v[1], L->a_v[2], L->s_v, L->c_v[0], L->c_v[1]};
    print_row("row", t, row, 6);   /* x F ua us uc x_target */
}

static void loop_free(loop_t *L)
{
    L->act.free_instance(L->a);
    L->sen.free_instance(L->s);
    L->com.free_instance(L->c);
}

static int cmd_loop(int argc, char **argv)
{
    if (argc < 5)
        return 2;
    loop_t L;
    double stop = atof(argv[3]), h = atof(argv[4]);
    loop_init(&L, argv, stop);
    loop_print(&L, 0.0);
    long n = lround(stop / h);
    for (long k = 0; k < n; k++) {
        loop_step(&L, k * h, h);
        loop_print(&L, (k + 1) * h);
    }
    loop_free(&L);
    return 0;
}

static int cmd_bench_loop(int argc, char **argv)
{
    if (argc < 5)
        return 2;
    loop_t L;
    long n = atol(argv[3]);
    double h = atof(argv[4]), best = 1e300;
    loop_init(&L, argv, 2 * 5 * n * h);
    long k = 0;
    for (int rep = 0; rep < 5; rep++) {
        double t0 = now();
        for (long i = 0; i < n; i++, k++)
            loop_step(&L, k * h, h);
        double us = (now() - t0) / n * 1e6;
        best = us < best ? us : best;
    }
    printf("loop_us_per_step %.4f\n", best);
    loop_free(&L);
    return 0;
}

/* -- bench: one FMI call, on this thread and on a thread of its own ------------------------------ */

typedef struct {
    fmu_t *f;
    fmi2Component c;
    long n;
    double step_us, call_us;
    long k0;
} bench_t;

static void bench_calls(bench_t *b)
{
    fmi2ValueReference in = 0, out = 1;
    double u = 1.0, y, best_step = 1e300, best_call = 1e300;
    long k = b->k0;
    for (int rep = 0; rep < 5; rep++) {
        double t0 = now();
        for (long i = 0; i < b->n; i++, k++)
            check(b->f->do_step(b->c, k * 1e-4, 1e-4, 1), "fmi2DoStep");
        double t1 = now();
        for (long i = 0; i < b->n; i++) {
            check(b->f->set_real(b->c, &in, 1, &u), "fmi2SetReal");
            check(b->f->get_real(b->c, &out, 1, &y), "fmi2GetReal");
        }
        double t2 = now();
        best_step = (t1 - t0) / b->n * 1e6 < best_step ? (t1 - t0) / b->n * 1e6 : best_step;
        best_call = (t2 - t1) / (2 * b->n) * 1e6 < best_call ? (t2 - t1) / (2 * b->n) * 1e6 : best_call;
    }
    b->step_us = best_step;
    b->call_us = best_call;
    b->k0 = k;
}

static void *bench_thread(void *arg)
{
    bench_calls(arg);
    return NULL;
}

static int cmd_bench(int argc, char **argv)
{
    if (argc < 2)
        return 2;
    fmu_t f;
    load(&f, argv[0]);
    bench_t b = {&f, NULL, atol(argv[1]), 0, 0, 0};
    b.c = make(&f, "bench", 0.0, 1e9);
    bench_calls(&b);
    printf("main_dostep_us %.4f\nmain_setget_us %.4f\n", b.step_us, b.call_us);
    pthread_t th;
    pthread_create(&th, NULL, bench_thread, &b);
    pthread_join(th, NULL);
    printf("thread_dostep_us %.4f\nthread_setget_us %.4f\n", b.step_us, b.call_us);
    f.free_instance(b.c);
    return 0;
}

/* -- orders: free and dlclose in mixed orders, reopen, exit with instances alive ----------------- */

static void steps(fmu_t *f, fmi2Component c, int n, long *k)
{
    for (int i = 0; i < n; i++, (*k)++)
        check(f->do_step(c, *k * 1e-4, 1e-4, 1), "fmi2DoStep");
}

static int cmd_orders(int argc, char **argv)
{
    if (argc < 3)
        return 2;
    fmu_t act, sen, com, act2;
    load(&act, argv[0]);
    load(&sen, argv[1]);
    fmi2Component a1 = make(&act, "a1", 0.0, 1.0), a2 = make(&act, "a2", 0.0, 1.0);
    fmi2Component s1 = make(&sen, "s1", 0.0, 1.0);
    load(&com, argv[2]);
    fmi2Component c1 = make(&com, "c1", 0.0, 1.0);
    long ka = 0, ka2 = 0, ks = 0, kc = 0;
    steps(&act, a1, 5, &ka);
    steps(&act, a2, 5, &ka2);
    steps(&sen, s1, 5, &ks);
    steps(&com, c1, 5, &kc);
    act.free_instance(a2);                 /* the second instance first */
    act.free_instance(a1);
    dlclose(act.lib);                      /* the FMU that started Python is gone ... */
    steps(&sen, s1, 5, &ks);               /* ... the others go on */
    steps(&com, c1, 5, &kc);
    load(&act2, argv[0]);                  /* reopened: a fresh copy of the FMI layer */
    fmi2Component a3 = make(&act2, "a3", 0.0, 1.0);
    long k3 = 0;
    steps(&act2, a3, 5, &k3);
    com.free_instance(c1);
    dlclose(com.lib);
    steps(&sen, s1, 5, &ks);
    steps(&act2, a3, 5, &k3);
    printf("orders ok\n");                 /* exit with a3 and s1 alive and their libraries open */
    return 0;
}

int main(int argc, char **argv)
{
    setvbuf(stdout, NULL, _IOFBF, 1 << 16);
    int i = 1;
    while (i + 1 < argc && argv[i][0] == '-') {
        if (strcmp(argv[i], "--preload") == 0) {
            /* a host that brought its own Python library (not started): the runtime must use it */
            if (!dlopen(argv[i + 1], RTLD_NOW | RTLD_GLOBAL)) {
                printf("fail preload %s\n", dlerror());
                return 3;
            }
        } else if (strcmp(argv[i], "--int") == 0 && n_ints < 8) {
            char id[256];
            unsigned vr;
            int value;
            if (sscanf(argv[i + 1], "%255[^:]:%u=%d", id, &vr, &value) != 3)
                return 2;
            snprintf(ints[n_ints].id, sizeof ints[n_ints].id, "%s", id);
            ints[n_ints].vr = vr;
            ints[n_ints++].value = value;
        } else {
            return 2;
        }
        i += 2;
    }
    if (i >= argc)
        return 2;
    const char *cmd = argv[i];
    int rc = 2;
    char **rest = argv + i + 1;
    int n = argc - i - 1;
    if (strcmp(cmd, "run") == 0) rc = cmd_run(n, rest);
    else if (strcmp(cmd, "churn") == 0) rc = cmd_churn(n, rest);
    else if (strcmp(cmd, "threads") == 0) rc = cmd_threads(n, rest);
    else if (strcmp(cmd, "nan") == 0) rc = cmd_nan(n, rest);
    else if (strcmp(cmd, "loop") == 0) rc = cmd_loop(n, rest);
    else if (strcmp(cmd, "bench") == 0) rc = cmd_bench(n, rest);
    else if (strcmp(cmd, "bench-loop") == 0) rc = cmd_bench_loop(n, rest);
    else if (strcmp(cmd, "orders") == 0) rc = cmd_orders(n, rest);
    if (rc == 0)
        printf("errors %d\nstatus ok\n", n_errors);
    else if (rc == 2)
        printf("usage error\n");
    return rc;
}
