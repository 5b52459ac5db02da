/* A fake Force Dimension SDK for tests: the DHD calls hapticd uses, over
 * simulated devices, plus fake_* calls the tests use to move them, press their
 * buttons, read what they were given (force, effector mass, gravity
 * compensation, force limit, watchdog) and unplug them. Compiled with
 * -DFAKE_DRD it is a fake libdrd: the same DHD calls (the real libdrd holds
 * them too) plus the DRD calls for the initialisation state and automatic
 * initialisation. Built by the tests with the C compiler; never shipped.
 * Signatures follow the DHD and DRD APIs (char ID last). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_DEV 4
#define DHD_NO_ERROR 0
#define DHD_MOTOR_SATURATED 2
#define FAKE_TYPE_OMEGA3 33

static struct {
    int present, open, enabled, plugged, calibrated, gravity, memory_fault, drd_open;
    unsigned short serial;
    unsigned int buttons;
    double pos[3], vel[3], force[3], force_sum[3], max_force, effector_mass;
    unsigned char watchdog;
    int autoinits;
    /* A path to play, one sample per dhdGetPosition: (n, 3) positions and velocities. */
    double *path_pos, *path_vel;
    int path_n, reads, k;
} dev[MAX_DEV];
static int count = 0;
static int current = -1;
static int expert = 0;
static int block_autoinit = 0;
static char last_error[128] = "no error";
/* Every call that changes a device, in order: "open 0;enable 0 0;force 0 0 0 0;..." */
static char call_log[8192];
/* Every force each device applied (after its enable state and its limit), in order:
 * what a test reads as "sent to the device". */
#define FORCE_LOG_N 65536
static double force_log[MAX_DEV][FORCE_LOG_N][3];
static int force_log_n[MAX_DEV];

static void logf_(const char *fmt, int i, double a, double b, double c) {
    size_t n = strlen(call_log);
    if (n + 80 < sizeof call_log) snprintf(call_log + n, sizeof call_log - n, fmt, i, a, b, c);
}
static int fail(const char *msg) { snprintf(last_error, sizeof last_error, "%s", msg); return -1; }
static int pick(char id) {
    int i = id < 0 ? current : id;
    if (i < 0 || i >= count || !dev[i].open) return -1;
    return i;
}

/* -- test controls -- */
void fake_reset(int n) {
    for (int i = 0; i < MAX_DEV; i++) { free(dev[i].path_pos); free(dev[i].path_vel); }
    memset(dev, 0, sizeof dev);
    count = n < MAX_DEV ? n : MAX_DEV;
    for (int i = 0; i < count; i++) {
        dev[i].present = 1; dev[i].plugged = 1; dev[i].serial = 10001 + i; dev[i].max_force = 12.0;
        dev[i].calibrated = 1; dev[i].effector_mass = 0.19;
    }
    current = -1; expert = 0; block_autoinit = 0; call_log[0] = 0;
    memset(force_log_n, 0, sizeof force_log_n);
}
void fake_set_state(int i, double x, double y, double z, double vx, double vy, double vz) {
    dev[i].pos[0] = x; dev[i].pos[1] = y; dev[i].pos[2] = z;
    dev[i].vel[0] = vx; dev[i].vel[1] = vy; dev[i].vel[2] = vz;
}
/* Device i moves along n samples: read k (from 0) of dhdGetPosition gives sample k (the
 * last one once the path is over), and dhdGetLinearVelocity the same sample's velocity. */
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
int fake_watchdog(int i) { return dev[i].watchdog; }
double fake_max_force(int i) { return dev[i].max_force; }
double fake_effector_mass(int i) { return dev[i].effector_mass; }
int fake_gravity(int i) { return dev[i].gravity; }
int fake_autoinits(int i) { return dev[i].autoinits; }
void fake_set_buttons(int i, unsigned int mask) { dev[i].buttons = mask; }
void fake_set_calibrated(int i, int on) { dev[i].calibrated = on; }
void fake_set_memory_fault(int i, int on) { dev[i].memory_fault = on; }
void fake_block_autoinit(int on) { block_autoinit = on; }
const char *fake_log(void) { return call_log; }
void fake_unplug(int i) { dev[i].plugged = 0; dev[i].enabled = 0; for (int k = 0; k < 3; k++) dev[i].force[k] = 0; }

/* -- the DHD API subset -- */
int dhdGetDeviceCount(void) { return count; }
const char *dhdErrorGetLastStr(void) { return last_error; }
double dhdGetTime(void) { return 0.0; }
int dhdEnableExpertMode(void) { expert = 1; return DHD_NO_ERROR; }
int dhdDisableExpertMode(void) { expert = 0; return DHD_NO_ERROR; }

int dhdOpenID(char id) {
    if (id < 0 || id >= count || !dev[(int)id].plugged) return fail("no such device");
    if (dev[(int)id].open) return fail("device already open");
    dev[(int)id].open = 1; current = id; logf_("open %d;", id, 0, 0, 0); return id;
}
int dhdOpenSerial(int serial) {
    for (int i = 0; i < count; i++) if (dev[i].serial == serial) return dhdOpenID((char)i);
    return fail("no device with this serial number");
}
int dhdClose(char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    dev[i].open = 0; dev[i].enabled = 0; dev[i].drd_open = 0; logf_("close %d;", i, 0, 0, 0);
    return DHD_NO_ERROR;
}
int dhdGetSerialNumber(unsigned short *sn, char id) { int i = pick(id); if (i < 0) return fail("device not open"); *sn = dev[i].serial; return DHD_NO_ERROR; }
const char *dhdGetSystemName(char id) { return pick(id) < 0 ? NULL : "omega.3"; }
int dhdGetSystemType(char id) { return pick(id) < 0 ? fail("device not open") : FAKE_TYPE_OMEGA3; }
int dhdCheckControllerMemory(char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    return dev[i].memory_fault ? fail("controller memory: configuration corrupt") : DHD_NO_ERROR;
}
int dhdEnableForce(unsigned char on, char id) {
    int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("device not available");
    dev[i].enabled = on ? 1 : 0; logf_("enable %d %g;", i, on ? 1.0 : 0.0, 0, 0); return DHD_NO_ERROR;
}
int dhdSetWatchdog(unsigned char val, char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    if (!expert) return fail("expert mode disabled");
    dev[i].watchdog = val; return DHD_NO_ERROR;
}
int dhdSetMaxForce(double f, char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    dev[i].max_force = f; logf_("maxforce %d %g;", i, f, 0, 0); return DHD_NO_ERROR;
}
double dhdGetMaxForce(char id) { int i = pick(id); return i < 0 ? -1.0 : dev[i].max_force; }
int dhdSetEffectorMass(double mass, char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    if (!(mass >= 0.0)) return fail("invalid effector mass");
    dev[i].effector_mass = mass; logf_("mass %d %g;", i, mass, 0, 0); return DHD_NO_ERROR;
}
int dhdGetEffectorMass(double *mass, char id) { int i = pick(id); if (i < 0) return fail("device not open"); *mass = dev[i].effector_mass; return DHD_NO_ERROR; }
int dhdSetGravityCompensation(int on, char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    dev[i].gravity = on ? 1 : 0; logf_("gravity %d %g;", i, on ? 1.0 : 0.0, 0, 0); return DHD_NO_ERROR;
}
unsigned int dhdGetButtonMask(char id) { int i = pick(id); return i < 0 ? 0 : dev[i].buttons; }

int dhdGetPosition(double *x, double *y, double *z, char id) {
    int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("USB error: device unplugged");
    if (dev[i].path_n > 0) {
        int k = dev[i].reads < dev[i].path_n ? dev[i].reads : dev[i].path_n - 1;
        dev[i].k = k; dev[i].reads++;
        for (int c = 0; c < 3; c++) { dev[i].pos[c] = dev[i].path_pos[3 * k + c]; dev[i].vel[c] = dev[i].path_vel[3 * k + c]; }
    }
    *x = dev[i].pos[0]; *y = dev[i].pos[1]; *z = dev[i].pos[2]; return DHD_NO_ERROR;
}
int dhdGetLinearVelocity(double *x, double *y, double *z, char id) {
    int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("USB error: device unplugged");
    *x = dev[i].vel[0]; *y = dev[i].vel[1]; *z = dev[i].vel[2]; return DHD_NO_ERROR;
}
int dhdSetForce(double fx, double fy, double fz, char id) {
    int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("USB error: device unplugged");
    double f[3] = {fx, fy, fz}, n = sqrt(fx * fx + fy * fy + fz * fz), s = 1.0; int r = DHD_NO_ERROR;
    if (n > dev[i].max_force) { s = dev[i].max_force / n; r = DHD_MOTOR_SATURATED; }
    for (int k = 0; k < 3; k++) { dev[i].force[k] = dev[i].enabled ? f[k] * s : 0.0; dev[i].force_sum[k] += dev[i].force[k]; }
    if (force_log_n[i] < FORCE_LOG_N) { memcpy(force_log[i][force_log_n[i]], dev[i].force, sizeof dev[i].force); force_log_n[i]++; }
    /* Only the first commands after opening are logged: enough to check the start sequence. */
    if (strlen(call_log) < 2048) logf_("force %d %g %g %g;", i, fx, fy, fz);
    return r;
}

#ifdef FAKE_DRD
/* -- the DRD API subset: initialisation state and automatic initialisation -- */
int drdOpenID(char id) {
    int r = dhdOpenID(id);
    if (r >= 0) dev[r].drd_open = 1;
    return r;
}
int drdClose(char id) { return dhdClose(id); }
/* The state is the controller's: any open device can be asked. */
_Bool drdIsInitialized(char id) { int i = pick(id); return i >= 0 && dev[i].calibrated; }
int drdAutoInit(char id) {
    int i = pick(id); if (i < 0 || !dev[i].drd_open) return fail("device not open through drdOpenID");
    if (block_autoinit) return fail("initialization failed: an end stop was not reached");
    dev[i].autoinits++; dev[i].calibrated = 1;
    for (int k = 0; k < 3; k++) { dev[i].pos[k] = 0.0; dev[i].vel[k] = 0.0; }
    logf_("autoinit %d;", i, 0, 0, 0);
    return DHD_NO_ERROR;
}
int drdStop(_Bool frc, char id) {
    int i = pick(id); if (i < 0) return fail("device not open");
    if (!frc) dev[i].enabled = 0;
    logf_("drdstop %d %g;", i, frc ? 1.0 : 0.0, 0, 0);
    return DHD_NO_ERROR;
}
#endif
