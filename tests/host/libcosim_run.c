/* PiezoSystem.ssp in libcosim driven from C (tests/test_runtime.py compiles it against the
 * libcosimc.so of the libcosimpy wheel; libcosim's C API, declared here from its documented
 * signatures: only what this program calls).
 *
 *   libcosim_run [--fixed-step] SSP STEP_NS STOP_NS [INSTANCE.VARIABLE]...
 *
 * prints "row t" and the Real columns (default: Actuator.x Sensor.us Compensator.uc
 * Compensator.x_target) per communication point (C99 hex doubles), then
 * "us_per_step <wall time of simulate_until per step>" and "status ok"; times are integer
 * nanoseconds.
 *
 * The algorithm is the SSD's (cosim_ssp_execution_create): the fixed-step algorithm of its OSP
 * annotation <osp:FixedStepAlgorithm baseStepSize=".." numWorkerThreads=".."/> (required: libcosim
 * does not check for it), whose step must be STEP_NS (checked on the recorded times).
 * numWorkerThreads="0" steps the FMUs on this thread, one after the other; without it libcosim keeps a pool of hardware_concurrency() - 1 worker threads
 * and hands every FMU's step to it and back (bench_runtime's docstring: where the time goes).
 * --fixed-step: cosim_ssp_fixed_step_execution_create(STEP_NS) instead (what libcosimpy's
 * CosimExecution.from_ssp_file(step_size=..) does): the SSD's algorithm is ignored, so libcosim's
 * default pool.
 */
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct cosim_execution_s cosim_execution;
typedef struct cosim_observer_s cosim_observer;
typedef struct {
    char name[1024];
    int index;
} cosim_slave_info;
typedef struct {
    char name[1024];
    uint32_t reference;
    int type, causality, variability;
} cosim_variable_description;

cosim_execution *cosim_ssp_execution_create(const char *ssp, bool start_defined, int64_t start);
cosim_execution *cosim_ssp_fixed_step_execution_create(const char *ssp, bool start_defined, int64_t start,
                                                       int64_t step);
int cosim_execution_destroy(cosim_execution *e);
size_t cosim_execution_get_num_slaves(cosim_execution *e);
int cosim_execution_get_slave_infos(cosim_execution *e, cosim_slave_info infos[], size_t n);
int cosim_slave_get_num_variables(cosim_execution *e, int slave);
int cosim_slave_get_variables(cosim_execution *e, int slave, cosim_variable_description v[], size_t n);
cosim_observer *cosim_time_series_observer_create(void);
int cosim_execution_add_observer(cosim_execution *e, cosim_observer *o);
int cosim_observer_start_observing(cosim_observer *o, int slave, int type, uint32_t vr);
int cosim_execution_simulate_until(cosim_execution *e, int64_t target);
int64_t cosim_observer_slave_get_real_samples(cosim_observer *o, int slave, uint32_t vr, int64_t from, size_t n,
                                              double values[], int64_t steps[], int64_t times[]);
int cosim_observer_destroy(cosim_observer *o);
const char *cosim_last_error_message(void);
void cosim_log_set_output_level(int level);

#define REAL 0
#define LOG_WARNING 3

static void die(const char *what)
{
    printf("fail %s: %s\n", what, cosim_last_error_message());
    exit(3);
}

static int slave_index(cosim_execution *e, const char *name)
{
    size_t n = cosim_execution_get_num_slaves(e);
    cosim_slave_info *infos = calloc(n, sizeof *infos);
    if (cosim_execution_get_slave_infos(e, infos, n) != 0)
        die("slave infos");
    int found = -1;
    for (size_t i = 0; i < n; i++)
        if (strcmp(infos[i].name, name) == 0)
            found = infos[i].index;
    free(infos);
    if (found < 0)
        die(name);
    return found;
}

static uint32_t value_reference(cosim_execution *e, int slave, const char *name)
{
    int n = cosim_slave_get_num_variables(e, slave);
    cosim_variable_description *v = calloc((size_t)n, sizeof *v);
    if (n < 0 || cosim_slave_get_variables(e, slave, v, (size_t)n) < 0)
        die("variables");
    for (int i = 0; i < n; i++)
        if (strcmp(v[i].name, name) == 0 && v[i].type == REAL) {
            uint32_t vr = v[i].reference;
            free(v);
            return vr;
        }
    die(name);
    return 0;
}

int main(int argc, char **argv)
{
    bool fixed_step = argc > 1 && strcmp(argv[1], "--fixed-step") == 0;
    argc -= fixed_step;
    argv += fixed_step;
    if (argc < 4)
        return 2;
    int64_t step = atoll(argv[2]), stop = atoll(argv[3]);
    if (step <= 0 || stop < step)
        return 2;
    cosim_log_set_output_level(getenv("LC_DEBUG") ? 0 : LOG_WARNING);
    cosim_execution *e = fixed_step ? cosim_ssp_fixed_step_execution_create(argv[1], false, 0, step)
                                    : cosim_ssp_execution_create(argv[1], false, 0);
    if (!e)
        die("execution");
    static const char *defaults[] = {"Actuator.x", "Sensor.us", "Compensator.uc", "Compensator.x_target"};
    int n_cols = argc > 4 ? argc - 4 : 4;
    if (n_cols > 16)
        return 2;
    int idx[16];
    uint32_t vr[16];
    cosim_observer *o = cosim_time_series_observer_create();
    if (!o || cosim_execution_add_observer(e, o) != 0)
        die("observer");
    for (int c = 0; c < n_cols; c++) {
        char col[2048];
        snprintf(col, sizeof col, "%s", argc > 4 ? argv[4 + c] : defaults[c]);
        char *dot = strchr(col, '.');
        if (!dot)
            return 2;
        *dot = '\0';
        idx[c] = slave_index(e, col);
        vr[c] = value_reference(e, idx[c], dot + 1);
        if (cosim_observer_start_observing(o, idx[c], REAL, vr[c]) != 0)
            die("observe");
    }
    struct timespec t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    if (cosim_execution_simulate_until(e, stop) != 1)   /* 1: reached the target time */
        die("simulate");
    clock_gettime(CLOCK_MONOTONIC, &t1);
    size_t m = (size_t)(stop / step) + 2;
    double *val[16];
    int64_t *steps = calloc(m, sizeof *steps), *times = calloc(m, sizeof *times), count = -1;
    for (int c = 0; c < n_cols; c++) {
        val[c] = calloc(m, sizeof(double));
        int64_t got = cosim_observer_slave_get_real_samples(o, idx[c], vr[c], 0, m, val[c], steps, times);
        count = count < 0 || got < count ? got : count;
    }
    /* the SSD's step is STEP_NS: one sample per step from 0 to STOP_NS */
    if (count != stop / step + 1 || times[1] - times[0] != step) {
        printf("fail step: the execution's step is not STEP_NS (%lld samples, first step %lld ns)\n",
               (long long)count, (long long)(count > 1 ? times[1] - times[0] : 0));
        return 3;
    }
    for (int64_t k = 0; k < count; k++) {
        printf("row %a", times[k] * 1e-9);
        for (int c = 0; c < n_cols; c++)
            printf(" %a", val[c][k]);
        printf("\n");
    }
    double wall = (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
    printf("us_per_step %.4f\n", wall / (double)(stop / step) * 1e6);
    cosim_execution_destroy(e);
    cosim_observer_destroy(o);
    printf("status ok\n");
    return 0;
}
