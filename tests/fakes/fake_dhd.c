/* A fake Force Dimension SDK: the DHD calls hapticd uses, over simulated devices,
 * plus fake_* calls the tests use to move them, press their buttons, read what they
 * were given (force, effector mass, gravity compensation, force limit, watchdog,
 * brakes) and make them fail. Compiled with -DFAKE_DRD it is a fake libdrd: the same
 * DHD calls (the real libdrd holds them too) plus the DRD calls for opening, the
 * initialisation state and automatic initialisation. Never shipped.
 *
 * By default it behaves as the SDK's documentation and its public callers say:
 *  - errors return -1 and set a code for dhdErrorGetLast (enum dhd_errors) and a
 *    message for dhdErrorGetLastStr; an unplugged device answers DHD_ERROR_COM;
 *  - dhdOpenID/drdOpenID on a device already open return its ID;
 *  - drdIsInitialized answers only for a device opened through drdOpenID;
 *  - dhdGetSerialNumber fails (DHD_ERROR_NOT_AVAILABLE) on a device without one;
 *  - dhdGetLinearVelocity fails with DHD_ERROR_TIMEOUT unless two position updates
 *    (dhdGetPosition or dhdGetLinearVelocity calls) fall within its window, 20 ms;
 *  - dhdCheckControllerMemory returns DHD_ERROR_CONFIGURATION when the check fails;
 *  - drdStop(false) leaves the device in brake mode: no force until dhdSetBrakes(off);
 *    dhdStop turns forces off and puts the brakes on;
 *  - dhdGetStatus fills DHD_MAX_STATUS (17) entries: a force-off the SDK made itself
 *    (fake_force_off: the force button, the velocity threshold, the watchdog, ...) reads
 *    DHD_STATUS_FORCE 0 and its cause in DHD_STATUS_FORCE_OFF_CAUSE;
 *  - the set-force calls return DHD_MOTOR_SATURATED when a motor cannot deliver the
 *    force (above fake_set_saturation's magnitude, or the SDK's force limit): the force
 *    is scaled down;
 *  - on a model with a wrist or a gripper (omega.6/.7, sigma.7, lambda.7) dhdSetForce
 *    commands the translation only; dhdSetForceAndTorqueAndGripperForce all of them.
 * fake_set_legacy(flags) switches back to the older behaviours (FAKE_LEGACY_*).
 *
 * From a shell (scripts/fake_sdk.py builds it): with HAPTICD_FAKE_DHD_DEVICES=N set
 * when the library loads, it starts with N devices, configured from the environment
 * (HAPTICD_FAKE_DHD_* below; docs/devices.md lists them). Signatures follow the DHD
 * and DRD APIs (char ID last). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_DEV 4
#define DHD_NO_ERROR 0
#define DHD_ERROR 1
#define DHD_ERROR_COM 2
#define DHD_ERROR_NOT_AVAILABLE 6
#define DHD_ERROR_TIMEOUT 7
#define DHD_ERROR_EXPERT_MODE_DISABLED 9
#define DHD_ERROR_CONFIGURATION 14
#define DHD_ERROR_INVALID_INDEX 15
#define DHD_ERROR_DEVICE_IN_USE 20
#define DHD_ERROR_INVALID 21
#define DHD_TIMEGUARD 1
#define DHD_MOTOR_SATURATED 2
#define TYPE_OMEGA3 33
#define DHD_MAX_STATUS 17
#define DHD_STATUS_POWER 0
#define DHD_STATUS_CONNECTED 1
#define DHD_STATUS_STARTED 2
#define DHD_STATUS_IDLE 4
#define DHD_STATUS_FORCE 5
#define DHD_STATUS_BRAKE 6
#define DHD_STATUS_WRIST_DETECTED 8
#define DHD_STATUS_GRAVITY 10
#define DHD_STATUS_FORCE_OFF_CAUSE 14
#define DHD_STATUS_AXIS_CHECKED 16
#define DHD_FORCE_OFF_NONE 0
#define DHD_FORCE_OFF_SOFTWARE 4

#define FAKE_LEGACY_DRD_ANY_HANDLE 1   /* drdIsInitialized answers on a DHD handle */
#define FAKE_LEGACY_NO_VELOCITY_WINDOW 2 /* the velocity never times out */
#define FAKE_LEGACY_OPEN_TWICE_FAILS 4 /* opening an open device fails */
#define FAKE_LEGACY_NO_CODES 8         /* every error reads DHD_ERROR; memory fault -1 */

static struct {
    int present, open, enabled, plugged, calibrated, gravity, memory_fault, drd_open;
    int has_serial, in_use, brakes, type, velocity_stuck, without_brakes_and_memory_check;
    unsigned short serial;
    unsigned int buttons;
    double pos[3], vel[3], force[3], force_sum[3], max_force, effector_mass;
    unsigned char watchdog;
    int autoinits;
    int forceoff_cause;     /* DHD_FORCE_OFF_*: why the forces went off last */
    double saturation;      /* above this force magnitude a motor saturates, N (0: the limit) */
    int saturated, timeguard; /* how many set-force calls returned each */
    int timeguard_every;    /* every n-th set-force call returns DHD_TIMEGUARD (0: none) */
    int set_calls;          /* set-force calls since the reset */
    double torque[3], gripper; /* the last wrist torques (N m) and gripper force (N) */
    int stops, velocity_threshold_sets;
    double updates[2]; /* the times of the last two position updates, s */
    /* A path to play, one sample per dhdGetPosition while forces are on: (n, 3). */
    double *path_pos, *path_vel;
    int path_n, reads, k;
} dev[MAX_DEV];
static int count = 0;
static int current = -1;
static int expert = 0;
static int block_autoinit = 0;
static int legacy = 0;
static int sdk_version[4] = {3, 17, 5, 0};
static double window_s = 0.020;
static int last_code = DHD_NO_ERROR;
static char last_error[128] = "no error";
/* From the environment (a shell): a motion about a point, and a file for the calibration. */
static int motion = 0;
static double motion_at[3], motion_amp[3], motion_period_s = 2.0, t_load;
static char state_file[512];
/* Every call that changes a device, in order: "open 0;enable 0 0;force 0 0 0 0;..." */
static char call_log[8192];
/* Every force each device applied (after its enable state, brakes and limit), in order:
 * what a test reads as "sent to the device". */
#define FORCE_LOG_N 65536
static double force_log[MAX_DEV][FORCE_LOG_N][3];
static int force_log_n[MAX_DEV];

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
static void logf_(const char *fmt, int i, double a, double b, double c) {
    size_t n = strlen(call_log);
    if (n + 80 < sizeof call_log) snprintf(call_log + n, sizeof call_log - n, fmt, i, a, b, c);
}
static int fail(int code, const char *msg) {
    last_code = (legacy & FAKE_LEGACY_NO_CODES) ? DHD_ERROR : code;
    snprintf(last_error, sizeof last_error, "%s", msg);
    return -1;
}
static int pick(char id) {
    int i = id < 0 ? current : id;
    if (i < 0 || i >= count || !dev[i].open) return -1;
    return i;
}
static int pick_live(char id, int *i) {
    *i = pick(id);
    if (*i < 0) return fail(DHD_ERROR_INVALID_INDEX, "device not open");
    if (!dev[*i].plugged) return fail(DHD_ERROR_COM, "USB error: device unplugged");
    return 0;
}
static void save_state(void) {
    if (!state_file[0]) return;
    FILE *f = fopen(state_file, "w");
    if (!f) return;
    for (int i = 0; i < count; i++) fputc(dev[i].calibrated ? '1' : '0', f);
    fputc('\n', f);
    fclose(f);
}

/* -- test controls -- */
void fake_reset(int n) {
    for (int i = 0; i < MAX_DEV; i++) { free(dev[i].path_pos); free(dev[i].path_vel); }
    memset(dev, 0, sizeof dev);
    count = n < MAX_DEV ? n : MAX_DEV;
    for (int i = 0; i < count; i++) {
        dev[i].present = 1; dev[i].plugged = 1; dev[i].serial = 10001 + i; dev[i].max_force = 12.0;
        dev[i].calibrated = 1; dev[i].effector_mass = 0.19; dev[i].has_serial = 1;
        dev[i].type = TYPE_OMEGA3;
    }
    current = -1; expert = 0; block_autoinit = 0; call_log[0] = 0; window_s = 0.020;
    last_code = DHD_NO_ERROR; motion = 0; state_file[0] = 0;
    sdk_version[0] = 3; sdk_version[1] = 17; sdk_version[2] = 5; sdk_version[3] = 0;
    memset(force_log_n, 0, sizeof force_log_n);
}
void fake_set_legacy(int flags) { legacy = flags; }
/* The SDK turns device i's forces off by itself, for a DHD_FORCE_OFF_* cause (1 button,
 * 2 velocity threshold, 3 watchdog, 4 software, 5 USB disconnection, 6 deadman): forces
 * off, and brakes on for those that brake (the velocity threshold, the watchdog). */
void fake_force_off(int i, int cause) {
    dev[i].enabled = 0; dev[i].forceoff_cause = cause;
    if (cause == 2 || cause == 3) dev[i].brakes = 1;
    for (int k = 0; k < 3; k++) dev[i].force[k] = 0.0;
    logf_("forceoff %d %g;", i, cause, 0, 0);
}
void fake_set_saturation(int i, double n) { dev[i].saturation = n; }
void fake_set_timeguard_every(int i, int n) { dev[i].timeguard_every = n; }
int fake_saturated(int i) { return dev[i].saturated; }
int fake_timeguards(int i) { return dev[i].timeguard; }
int fake_stops(int i) { return dev[i].stops; }
int fake_velocity_threshold_sets(int i) { return dev[i].velocity_threshold_sets; }
/* The last wrist torques and gripper force device i was given: (4,). */
void fake_get_torque_and_gripper(int i, double *out) {
    for (int k = 0; k < 3; k++) out[k] = dev[i].torque[k];
    out[3] = dev[i].gripper;
}
void fake_set_state(int i, double x, double y, double z, double vx, double vy, double vz) {
    dev[i].pos[0] = x; dev[i].pos[1] = y; dev[i].pos[2] = z;
    dev[i].vel[0] = vx; dev[i].vel[1] = vy; dev[i].vel[2] = vz;
}
/* Device i moves along n samples: read k (from 0) of dhdGetPosition while its forces are
 * on gives sample k (the last one once the path is over), and dhdGetLinearVelocity the
 * same sample's velocity. Reads with forces off (before the run) do not move it. */
void fake_set_path(int i, int n, const double *pos, const double *vel) {
    free(dev[i].path_pos); free(dev[i].path_vel);
    dev[i].path_pos = malloc(sizeof(double) * 3 * n); dev[i].path_vel = malloc(sizeof(double) * 3 * n);
    memcpy(dev[i].path_pos, pos, sizeof(double) * 3 * n); memcpy(dev[i].path_vel, vel, sizeof(double) * 3 * n);
    dev[i].path_n = n; dev[i].reads = 0; dev[i].k = 0;
}
int fake_reads(int i) { return dev[i].reads; }
/* Copies at most max of device i's applied forces into out (max, 3); returns how many. */
int fake_force_log(int i, double *out, int max) {
    int n = force_log_n[i] < max ? force_log_n[i] : max;
    memcpy(out, force_log[i], sizeof(double) * 3 * (size_t)n);
    return n;
}
void fake_get_force(int i, double *f) { for (int k = 0; k < 3; k++) f[k] = dev[i].force[k]; }
/* The sum of every force the device applied since the reset, N. */
void fake_get_force_sum(int i, double *f) { for (int k = 0; k < 3; k++) f[k] = dev[i].force_sum[k]; }
int fake_is_enabled(int i) { return dev[i].enabled; }
int fake_is_open(int i) { return dev[i].open; }
int fake_brakes(int i) { return dev[i].brakes; }
int fake_watchdog(int i) { return dev[i].watchdog; }
double fake_max_force(int i) { return dev[i].max_force; }
double fake_effector_mass(int i) { return dev[i].effector_mass; }
int fake_gravity(int i) { return dev[i].gravity; }
int fake_autoinits(int i) { return dev[i].autoinits; }
void fake_set_buttons(int i, unsigned int mask) { dev[i].buttons = mask; }
void fake_set_calibrated(int i, int on) { dev[i].calibrated = on; }
void fake_set_memory_fault(int i, int on) { dev[i].memory_fault = on; }
void fake_set_serial(int i, int has) { dev[i].has_serial = has; }
void fake_set_type(int i, int type) { dev[i].type = type; }
void fake_set_in_use(int i, int on) { dev[i].in_use = on; }
void fake_set_velocity_stuck(int i, int on) { dev[i].velocity_stuck = on; }
/* A model without brakes and without the controller memory check: both calls fail with
 * DHD_ERROR_NOT_AVAILABLE. */
void fake_set_basic(int i, int on) { dev[i].without_brakes_and_memory_check = on; }
void fake_set_velocity_window(double s) { window_s = s; }
void fake_set_sdk_version(int major, int minor, int release, int revision) {
    sdk_version[0] = major; sdk_version[1] = minor; sdk_version[2] = release; sdk_version[3] = revision;
}
void fake_block_autoinit(int on) { block_autoinit = on; }
const char *fake_log(void) { return call_log; }
void fake_replug(int i) { dev[i].plugged = 1; dev[i].open = 0; dev[i].drd_open = 0; }
void fake_unplug(int i) { dev[i].plugged = 0; dev[i].enabled = 0; for (int k = 0; k < 3; k++) dev[i].force[k] = 0; }

/* -- from the environment, when the library loads (a person's shell, not the tests) -- */
static void env_vec(const char *name, double *v) {
    const char *s = getenv(name);
    if (s) sscanf(s, "%lf,%lf,%lf", &v[0], &v[1], &v[2]);
}
static int env_int(const char *name, int dflt) {
    const char *s = getenv(name);
    return s && *s ? atoi(s) : dflt;
}
__attribute__((constructor)) static void from_environment(void) {
    const char *n = getenv("HAPTICD_FAKE_DHD_DEVICES");
    t_load = now_s();
    if (!n || !*n) return;
    fake_reset(atoi(n));
    int type = env_int("HAPTICD_FAKE_DHD_TYPE", TYPE_OMEGA3);
    int serials = env_int("HAPTICD_FAKE_DHD_SERIALS", 1);
    int calibrated = env_int("HAPTICD_FAKE_DHD_CALIBRATED", 1);
    for (int i = 0; i < count; i++) {
        dev[i].type = type; dev[i].has_serial = serials; dev[i].calibrated = calibrated;
    }
    const char *v = getenv("HAPTICD_FAKE_DHD_SDK_VERSION");
    if (v) sscanf(v, "%d.%d.%d", &sdk_version[0], &sdk_version[1], &sdk_version[2]);
    legacy = env_int("HAPTICD_FAKE_DHD_LEGACY", 0);
    const char *m = getenv("HAPTICD_FAKE_DHD_MOTION");
    motion = m && strcmp(m, "sine") == 0;
    env_vec("HAPTICD_FAKE_DHD_POSITION", motion_at);
    env_vec("HAPTICD_FAKE_DHD_AMPLITUDE", motion_amp);
    const char *p = getenv("HAPTICD_FAKE_DHD_PERIOD_S");
    if (p && atof(p) > 0) motion_period_s = atof(p);
    for (int i = 0; i < count; i++) fake_set_state(i, motion_at[0], motion_at[1], motion_at[2], 0, 0, 0);
    const char *f = getenv("HAPTICD_FAKE_DHD_STATE");
    if (f && *f) {
        snprintf(state_file, sizeof state_file, "%s", f);
        FILE *fp = fopen(state_file, "r");
        if (fp) {
            for (int i = 0; i < count; i++) {
                int c = fgetc(fp);
                if (c == '0' || c == '1') dev[i].calibrated = c == '1';
            }
            fclose(fp);
        }
    }
}
static void move(int i) {
    if (dev[i].path_n > 0) {
        if (!dev[i].enabled) return;
        int k = dev[i].reads < dev[i].path_n ? dev[i].reads : dev[i].path_n - 1;
        dev[i].k = k; dev[i].reads++;
        for (int c = 0; c < 3; c++) { dev[i].pos[c] = dev[i].path_pos[3 * k + c]; dev[i].vel[c] = dev[i].path_vel[3 * k + c]; }
    } else if (motion) {
        double w = 2.0 * M_PI / motion_period_s, t = now_s() - t_load;
        for (int c = 0; c < 3; c++) {
            dev[i].pos[c] = motion_at[c] + motion_amp[c] * sin(w * t);
            dev[i].vel[c] = motion_amp[c] * w * cos(w * t);
        }
    }
}
static void position_update(int i) { dev[i].updates[0] = dev[i].updates[1]; dev[i].updates[1] = now_s(); }

/* -- the DHD API subset -- */
int dhdGetDeviceCount(void) { return count; }
int dhdErrorGetLast(void) { return last_code; }
const char *dhdErrorGetLastStr(void) { return last_error; }
void dhdGetSDKVersion(int *major, int *minor, int *release, int *revision) {
    *major = sdk_version[0]; *minor = sdk_version[1]; *release = sdk_version[2]; *revision = sdk_version[3];
}
double dhdGetTime(void) { return now_s(); }
int dhdEnableExpertMode(void) { expert = 1; return DHD_NO_ERROR; }
int dhdDisableExpertMode(void) { expert = 0; return DHD_NO_ERROR; }

int dhdOpenID(char id) {
    if (id < 0 || id >= count) return fail(DHD_ERROR_INVALID_INDEX, "no such device");
    int i = id;
    if (!dev[i].plugged) return fail(DHD_ERROR_COM, "USB error: device unplugged");
    if (dev[i].in_use) return fail(DHD_ERROR_DEVICE_IN_USE, "device in use by another program");
    if (dev[i].open) {
        if (legacy & FAKE_LEGACY_OPEN_TWICE_FAILS) return fail(DHD_ERROR_DEVICE_IN_USE, "device already open");
        current = i; return i;
    }
    dev[i].open = 1; current = i; dev[i].updates[0] = dev[i].updates[1] = -1e9;
    logf_("open %d;", i, 0, 0, 0); return i;
}
int dhdClose(char id) {
    int i = pick(id); if (i < 0) return fail(DHD_ERROR_INVALID_INDEX, "device not open");
    dev[i].open = 0; dev[i].enabled = 0; dev[i].drd_open = 0; logf_("close %d;", i, 0, 0, 0);
    return DHD_NO_ERROR;
}
int dhdGetSerialNumber(unsigned short *sn, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (!dev[i].has_serial) return fail(DHD_ERROR_NOT_AVAILABLE, "serial number not available on this device");
    *sn = dev[i].serial; return DHD_NO_ERROR;
}
const char *dhdGetSystemName(char id) {
    int i = pick(id); if (i < 0) return NULL;
    switch (dev[i].type) {
    case 33: return "omega.3";
    case 63: return "delta.3";
    case 60: return "Falcon";
    case 34: case 36: return "omega.6";
    case 35: case 37: return "omega.7";
    case 104: case 105: return "sigma.7";
    case 108: case 109: return "lambda.7";
    case 91: return "custom";
    default: return "unknown";
    }
}
int dhdGetSystemType(char id) { int i; if (pick_live(id, &i) < 0) return -1; return dev[i].type; }
int dhdCheckControllerMemory(char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (dev[i].without_brakes_and_memory_check) return fail(DHD_ERROR_NOT_AVAILABLE, "not available on this device");
    if (!dev[i].memory_fault) return DHD_NO_ERROR;
    if (legacy & FAKE_LEGACY_NO_CODES) return fail(DHD_ERROR, "controller memory: configuration corrupt");
    return DHD_ERROR_CONFIGURATION;
}
int dhdEnableForce(unsigned char on, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    dev[i].enabled = on ? 1 : 0; dev[i].forceoff_cause = on ? DHD_FORCE_OFF_NONE : DHD_FORCE_OFF_SOFTWARE;
    logf_("enable %d %g;", i, on ? 1.0 : 0.0, 0, 0); return DHD_NO_ERROR;
}
int dhdSetBrakes(int on, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (dev[i].without_brakes_and_memory_check) return fail(DHD_ERROR_NOT_AVAILABLE, "not available on this device");
    dev[i].brakes = on ? 1 : 0; logf_("brakes %d %g;", i, on ? 1.0 : 0.0, 0, 0); return DHD_NO_ERROR;
}
int dhdSetWatchdog(unsigned char val, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (!expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED, "expert mode disabled");
    dev[i].watchdog = val; return DHD_NO_ERROR;
}
int dhdSetMaxForce(double f, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    dev[i].max_force = f; logf_("maxforce %d %g;", i, f, 0, 0); return DHD_NO_ERROR;
}
double dhdGetMaxForce(char id) { int i = pick(id); return i < 0 ? -1.0 : dev[i].max_force; }
int dhdSetEffectorMass(double mass, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (!(mass >= 0.0)) return fail(DHD_ERROR_INVALID, "invalid effector mass");
    dev[i].effector_mass = mass; logf_("mass %d %g;", i, mass, 0, 0); return DHD_NO_ERROR;
}
int dhdGetEffectorMass(double *mass, char id) { int i; if (pick_live(id, &i) < 0) return -1; *mass = dev[i].effector_mass; return DHD_NO_ERROR; }
int dhdSetGravityCompensation(int on, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    dev[i].gravity = on ? 1 : 0; logf_("gravity %d %g;", i, on ? 1.0 : 0.0, 0, 0); return DHD_NO_ERROR;
}
unsigned int dhdGetButtonMask(char id) { int i = pick(id); return i < 0 ? 0 : dev[i].buttons; }

int dhdGetPosition(double *x, double *y, double *z, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    move(i);
    position_update(i);
    *x = dev[i].pos[0]; *y = dev[i].pos[1]; *z = dev[i].pos[2]; return DHD_NO_ERROR;
}
int dhdGetLinearVelocity(double *x, double *y, double *z, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    /* The estimator needs two position updates within its window before this call. */
    int stale = now_s() - dev[i].updates[0] > window_s;
    position_update(i);
    if (dev[i].velocity_stuck || (stale && !(legacy & FAKE_LEGACY_NO_VELOCITY_WINDOW)))
        return fail(DHD_ERROR_TIMEOUT, "timeout: too few position updates for the velocity estimate");
    *x = dev[i].vel[0]; *y = dev[i].vel[1]; *z = dev[i].vel[2]; return DHD_NO_ERROR;
}
static int wrist_or_gripper(int i) {
    switch (dev[i].type) {
    case 34: case 35: case 36: case 37: case 104: case 105: case 108: case 109: return 1;
    default: return 0;
    }
}
/* One set-force call: the force after the enable state, brakes, saturation and limit. */
static int apply_force(int i, double fx, double fy, double fz) {
    double f[3] = {fx, fy, fz}, n = sqrt(fx * fx + fy * fy + fz * fz), s = 1.0; int r = DHD_NO_ERROR;
    double cap = dev[i].saturation > 0 && dev[i].saturation < dev[i].max_force ? dev[i].saturation : dev[i].max_force;
    dev[i].set_calls++;
    if (dev[i].timeguard_every > 0 && dev[i].set_calls % dev[i].timeguard_every == 0) {
        dev[i].timeguard++; return DHD_TIMEGUARD; /* not sent: too soon after the last */
    }
    if (n > cap) { s = cap / n; r = DHD_MOTOR_SATURATED; dev[i].saturated++; }
    int on = dev[i].enabled && !dev[i].brakes;
    for (int k = 0; k < 3; k++) { dev[i].force[k] = on ? f[k] * s : 0.0; dev[i].force_sum[k] += dev[i].force[k]; }
    if (force_log_n[i] < FORCE_LOG_N) { memcpy(force_log[i][force_log_n[i]], dev[i].force, sizeof dev[i].force); force_log_n[i]++; }
    return r;
}
int dhdSetForce(double fx, double fy, double fz, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    /* Only the first commands after opening are logged: enough to check the start sequence. */
    if (strlen(call_log) < 2048) logf_("force %d %g %g %g;", i, fx, fy, fz);
    return apply_force(i, fx, fy, fz);
}
int dhdSetForceAndTorqueAndGripperForce(double fx, double fy, double fz, double tx, double ty, double tz, double fg, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    dev[i].torque[0] = tx; dev[i].torque[1] = ty; dev[i].torque[2] = tz; dev[i].gripper = fg;
    if (strlen(call_log) < 2048) logf_("force7 %d %g %g %g;", i, fx, fy, fz);
    return apply_force(i, fx, fy, fz);
}
int dhdGetStatus(int status[DHD_MAX_STATUS], char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    memset(status, 0, sizeof(int) * DHD_MAX_STATUS);
    status[DHD_STATUS_POWER] = 1; status[DHD_STATUS_CONNECTED] = 1; status[DHD_STATUS_STARTED] = 1;
    status[DHD_STATUS_IDLE] = !dev[i].enabled; status[DHD_STATUS_FORCE] = dev[i].enabled;
    status[DHD_STATUS_BRAKE] = dev[i].brakes; status[DHD_STATUS_WRIST_DETECTED] = wrist_or_gripper(i);
    status[DHD_STATUS_GRAVITY] = dev[i].gravity; status[DHD_STATUS_FORCE_OFF_CAUSE] = dev[i].forceoff_cause;
    status[DHD_STATUS_AXIS_CHECKED] = 1;
    return DHD_NO_ERROR;
}
/* Forces off and the brakes on (the SDK's safe state before closing). */
int dhdStop(char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    dev[i].enabled = 0; dev[i].brakes = 1; dev[i].stops++; dev[i].forceoff_cause = DHD_FORCE_OFF_SOFTWARE;
    for (int k = 0; k < 3; k++) dev[i].force[k] = 0.0;
    logf_("stop %d;", i, 0, 0, 0);
    return DHD_NO_ERROR;
}
int dhdSetVelocityThreshold(unsigned int val, char id) {
    int i; if (pick_live(id, &i) < 0) return -1;
    if (!expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED, "expert mode disabled");
    dev[i].velocity_threshold_sets++; logf_("velocitythreshold %d %g;", i, (double)val, 0, 0);
    return DHD_NO_ERROR;
}

#ifdef FAKE_DRD
/* -- the DRD API subset: opening, initialisation state and automatic initialisation -- */
int drdOpenID(char id) {
    int r = dhdOpenID(id);
    if (r >= 0) dev[r].drd_open = 1;
    return r;
}
int drdClose(char id) { return dhdClose(id); }
/* The state of a device DRD opened (documented); older fakes answered for any handle. */
_Bool drdIsInitialized(char id) {
    int i = pick(id);
    if (i < 0) return 0;
    if (!dev[i].drd_open && !(legacy & FAKE_LEGACY_DRD_ANY_HANDLE)) return 0;
    return dev[i].calibrated;
}
int drdAutoInit(char id) {
    int i = pick(id); if (i < 0 || !dev[i].drd_open) return fail(DHD_ERROR_INVALID_INDEX, "device not open through drdOpenID");
    if (block_autoinit) return fail(DHD_ERROR, "initialization failed: an end stop was not reached");
    dev[i].autoinits++; dev[i].calibrated = 1;
    for (int k = 0; k < 3; k++) { dev[i].pos[k] = 0.0; dev[i].vel[k] = 0.0; }
    logf_("autoinit %d;", i, 0, 0, 0);
    save_state();
    return DHD_NO_ERROR;
}
/* Stops the regulation: with frc false the device is left in brake mode, forces off. */
int drdStop(_Bool frc, char id) {
    int i = pick(id); if (i < 0) return fail(DHD_ERROR_INVALID_INDEX, "device not open");
    if (!frc) { dev[i].enabled = 0; dev[i].brakes = 1; }
    logf_("drdstop %d %g;", i, frc ? 1.0 : 0.0, 0, 0);
    return DHD_NO_ERROR;
}
#endif
