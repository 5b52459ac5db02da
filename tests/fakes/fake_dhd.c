/* A fake Force Dimension libdhd for tests: the DHD calls hapticd uses, over
 * simulated devices, plus fake_* calls the tests use to move them, read the
 * force they were given, and unplug them. Built by the tests with the C
 * compiler; never shipped. Signatures follow the DHD API (char ID last). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#define MAX_DEV 4
#define DHD_NO_ERROR 0
#define DHD_MOTOR_SATURATED 2

static struct {
    int present, open, enabled, plugged;
    unsigned short serial;
    double pos[3], vel[3], force[3], max_force;
    unsigned char watchdog;
} dev[MAX_DEV];
static int count = 0;
static int current = -1;
static char last_error[128] = "no error";

static int fail(const char *msg) { snprintf(last_error, sizeof last_error, "%s", msg); return -1; }
static int pick(char id) {
    int i = id < 0 ? current : id;
    if (i < 0 || i >= count || !dev[i].open) return -1;
    return i;
}

/* -- test controls -- */
void fake_reset(int n) {
    memset(dev, 0, sizeof dev);
    count = n < MAX_DEV ? n : MAX_DEV;
    for (int i = 0; i < count; i++) { dev[i].present = 1; dev[i].plugged = 1; dev[i].serial = 10001 + i; dev[i].max_force = 12.0; }
    current = -1;
}
void fake_set_state(int i, double x, double y, double z, double vx, double vy, double vz) {
    dev[i].pos[0] = x; dev[i].pos[1] = y; dev[i].pos[2] = z;
    dev[i].vel[0] = vx; dev[i].vel[1] = vy; dev[i].vel[2] = vz;
}
void fake_get_force(int i, double *f) { for (int k = 0; k < 3; k++) f[k] = dev[i].force[k]; }
int fake_is_enabled(int i) { return dev[i].enabled; }
int fake_watchdog(int i) { return dev[i].watchdog; }
void fake_unplug(int i) { dev[i].plugged = 0; dev[i].enabled = 0; for (int k = 0; k < 3; k++) dev[i].force[k] = 0; }

/* -- the DHD API subset -- */
int dhdGetDeviceCount(void) { return count; }
const char *dhdErrorGetLastStr(void) { return last_error; }
double dhdGetTime(void) { return 0.0; }

int dhdOpenID(char id) {
    if (id < 0 || id >= count || !dev[(int)id].plugged) return fail("no such device");
    dev[(int)id].open = 1; current = id; return id;
}
int dhdOpenSerial(int serial) {
    for (int i = 0; i < count; i++) if (dev[i].serial == serial) return dhdOpenID((char)i);
    return fail("no device with this serial number");
}
int dhdClose(char id) { int i = pick(id); if (i < 0) return fail("device not open"); dev[i].open = 0; dev[i].enabled = 0; return DHD_NO_ERROR; }
int dhdGetSerialNumber(unsigned short *sn, char id) { int i = pick(id); if (i < 0) return fail("device not open"); *sn = dev[i].serial; return DHD_NO_ERROR; }
const char *dhdGetSystemName(char id) { return pick(id) < 0 ? NULL : "fake omega.3"; }
int dhdEnableForce(unsigned char on, char id) { int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("device not available"); dev[i].enabled = on ? 1 : 0; return DHD_NO_ERROR; }
int dhdSetWatchdog(unsigned char val, char id) { int i = pick(id); if (i < 0) return fail("device not open"); dev[i].watchdog = val; return DHD_NO_ERROR; }
int dhdSetMaxForce(double f, char id) { int i = pick(id); if (i < 0) return fail("device not open"); dev[i].max_force = f; return DHD_NO_ERROR; }
double dhdGetMaxForce(char id) { int i = pick(id); return i < 0 ? -1.0 : dev[i].max_force; }
unsigned int dhdGetButtonMask(char id) { return 0; }

int dhdGetPosition(double *x, double *y, double *z, char id) {
    int i = pick(id); if (i < 0 || !dev[i].plugged) return fail("USB error: device unplugged");
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
    for (int k = 0; k < 3; k++) dev[i].force[k] = dev[i].enabled ? f[k] * s : 0.0;
    return r;
}
