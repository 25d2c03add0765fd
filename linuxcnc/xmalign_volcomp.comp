component xmalign_volcomp "Volumetric compensation of a trivkins machine from xmalign's rigid-body tables";

description """
Sits between the motion controller and the drives. Each servo period it takes the
commanded tool point (the joints' *pos-cmd*, trivkins: every joint is one axis),
computes the correction *c* that makes the rigid-body model of the table file
put the tool on the commanded point (*c* = -dp(k + c), first-order model of 18
error motions, 3 squareness errors, the kinematic chain and the tool offset)
and adds it to each joint's *motor-pos-cmd* on its way to the drive. Gantries
(two joints on one axis, coordinates=XYYZ) give both joints their axis's
correction.

Two functions. *command*, right after motion-controller, computes the
correction and writes the drives' commands. *feedback*, right before
motion-controller (after the drives' feedback is read), subtracts from each
drive's feedback the correction that was sent with the command the feedback
answers (the last period's), so the motion controller sees no following error
from the correction and no more delay than without the component.

The table file is written by *xmalign comp --controller linuxcnc-volumetric* and
read once when the component loads (uspace builds: rtapi_app is a user
process). A file that cannot be read, is damaged (its CRC-32 does not match) or
does not fit makes *loadrt* fail with the file, the line and the reason, so
LinuxCNC does not start.

When it applies: the correction follows the model only while *all-homed*
(motion.is-all-homed), every *joint-homed-N* (joint.N.homed) and
*motion-enabled* (motion.motion-enabled) are TRUE (*active*).
motion.is-all-homed alone is not enough: it reads TRUE before the motion
controller has activated its joints. With the machine on but a joint not homed,
the correction returns to zero (homing then takes place uncorrected, in the
frame the tables were measured in). With the machine off (E-stop; the drives
are disabled) the correction is held while the joints stay homed, and is set
to zero at once when they are not. The applied correction moves towards its
goal at most *max-rate* mm/s: no step when homing completes, the machine is
switched on or a joint is unhomed.

Safe limits: while the tool point lies outside the range the tables cover, or
the correction exceeds the file's bound, *ok* is FALSE and the correction is
held at its last value instead of following. When *ok* falls the component
trips: *enable-out* (wired to iocontrol.0.emc-enable-in) drops and LinuxCNC
goes to E-stop. The operator's E-stop reset (*reset*, wired to
iocontrol.0.user-request-enable) clears the trip, so the machine can be moved
back (the correction stays held until the tool point is back where it is
valid; a new trip needs *ok* to fall again).

Build and install: *halcompile --install linuxcnc/xmalign_volcomp.comp*.
""";

pin in float joint_pos_cmd_#[16 : personality] "joint.N.pos-cmd: commanded joint position, mm";
pin in float motor_pos_cmd_#[16 : personality] "joint.N.motor-pos-cmd: the motion controller's command";
pin out float motor_pos_out_#[16 : personality] "corrected command, to the drive";
pin in float motor_pos_fb_in_#[16 : personality] "the drive's feedback";
pin out float motor_pos_fb_out_#[16 : personality] "feedback less the correction, to joint.N.motor-pos-fb";
pin in bit joint_homed_#[16 : personality] "joint.N.homed";
pin in bit all_homed "motion.is-all-homed";
pin in bit motion_enabled "motion.motion-enabled: the machine is on";
pin out bit active "the correction follows the model: every joint homed, all-homed, machine on";
pin in bit enable_in "the E-stop chain's input (e.g. iocontrol.0.user-enable-out)";
pin out bit enable_out "enable-in unless tripped, to iocontrol.0.emc-enable-in";
pin out bit ok "FALSE while the position is outside the tables or the correction exceeds its bound";
pin out s32 fault "0 ok, 1 outside the tables, 2 correction beyond the bound";
pin out bit tripped "set when ok falls; cleared by reset or while enable-in is FALSE";
pin in bit reset "iocontrol.0.user-request-enable: the operator's E-stop reset clears the trip";
pin out float correction_#[3] "applied correction X, Y, Z, mm";
pin out float target_#[3] "model correction at the commanded point X, Y, Z, mm (0 until homed)";
pin in float max_rate = 1.0 "largest rate of change of the applied correction, mm/s";

option extra_setup yes;
option period no;

function feedback fp "before motion-controller: each drive's feedback less the correction sent with the command it answers";
function command fp "after motion-controller: the correction, added to each drive's command";
license "GPL";
author "xmalign";
;;

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#define MAX_POINTS 4096
#define LINE_LEN 512

static char *table = "";
RTAPI_MP_STRING(table, "path of the table file written by xmalign comp");

/* 18 error motions: axis K, then EXK EYK EZK EAK EBK ECK (mm and rad inside) */
static const char *NAMES[3][6] = {
    {"EXX", "EYX", "EZX", "EAX", "EBX", "ECX"},
    {"EXY", "EYY", "EZY", "EAY", "EBY", "ECY"},
    {"EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"},
};

typedef struct {
    int count;
    double position_mm[MAX_POINTS];
    double value[MAX_POINTS];
} error_table_t;

static error_table_t tables[3][6];
static int joint_axis[16];
static int joint_count;
static double lever[3][3];         /* 1 where axis J's coordinate enters axis K's lever arm */
static double tool_offset_mm[3];
static double squareness_rad[3];   /* EC0Y EA0Z EB0Z */
static double bound_mm;
static double cover_low_mm[3], cover_high_mm[3];
static double applied_mm[3];
static int last_code;

static unsigned long crc32_update(unsigned long crc, const char *text) {
    for (; *text; text++) {
        int bit;
        crc ^= (unsigned char)*text;
        for (bit = 0; bit < 8; bit++)
            crc = (crc >> 1) ^ (0xEDB88320UL & (0UL - (crc & 1UL)));
    }
    return crc;
}

static int fail(int line, const char *why) {
    rtapi_print_msg(RTAPI_MSG_ERR, "xmalign_volcomp: %s line %d: %s\n", table, line, why);
    return -EINVAL;
}

static int axis_of(char letter) {
    const char *found = strchr("XYZ", letter);
    return (letter && found) ? (int)(found - "XYZ") : -1;
}

static int find_name(const char *name, int *axis, int *index) {
    int k, i;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 6; i++)
            if (strcmp(name, NAMES[k][i]) == 0) {
                *axis = k;
                *index = i;
                return 0;
            }
    return -1;
}

/* Reads the file; every line but the last enters the CRC-32 that the last one states. */
static int read_table_file(void) {
    char line[LINE_LEN], word[64], letters[32];
    FILE *stream;
    unsigned long crc = 0xFFFFFFFFUL, stated;
    int number = 0, k, i, have_header = 0, have_crc = 0, seen_tables = 0;
    double a, b, c;
    error_table_t *current = NULL;
    int remaining = 0, scale_index = 0;

    if (!table || !*table)
        return fail(0, "no table file given (loadrt xmalign_volcomp table=PATH)");
    stream = fopen(table, "r");
    if (!stream)
        return fail(0, "cannot open the table file");
    joint_count = 0;
    bound_mm = -1;
    while (fgets(line, sizeof line, stream)) {
        number++;
        if (!strchr(line, '\n') && !feof(stream)) {
            fclose(stream);
            return fail(number, "line too long");
        }
        if (have_crc) {
            fclose(stream);
            return fail(number, "text after the crc32 line");
        }
        if (sscanf(line, "crc32 %lx", &stated) == 1) {
            have_crc = 1;
            if ((crc ^ 0xFFFFFFFFUL) != stated) {
                fclose(stream);
                return fail(number, "CRC-32 mismatch: the file is damaged or was edited; "
                                    "write it again with xmalign comp");
            }
            continue;
        }
        crc = crc32_update(crc, line);
        if (line[0] == '#' || line[0] == '\n')
            continue;
        if (remaining > 0) {
            int n = current->count - remaining;
            if (sscanf(line, "%lf %lf", &a, &b) != 2 || !isfinite(a) || !isfinite(b)) {
                fclose(stream);
                return fail(number, "expected two numbers: position_mm value");
            }
            if (n > 0 && a <= current->position_mm[n - 1]) {
                fclose(stream);
                return fail(number, "positions must be ascending");
            }
            current->position_mm[n] = a;
            current->value[n] = b * (scale_index < 3 ? 1e-3 : 1e-6); /* um -> mm, urad -> rad */
            remaining--;
            continue;
        }
        if (sscanf(line, "%63s", word) != 1) {
            fclose(stream);
            return fail(number, "unreadable line");
        }
        if (strcmp(word, "xmalign-volcomp") == 0) {
            if (sscanf(line, "%*s %d", &k) != 1 || k != 1) {
                fclose(stream);
                return fail(number, "not a version 1 table file");
            }
            have_header = 1;
        } else if (!have_header) {
            fclose(stream);
            return fail(number, "not an xmalign-volcomp table file (first line)");
        } else if (strcmp(word, "coordinates") == 0) {
            if (sscanf(line, "%*s %31s", letters) != 1 || strlen(letters) > 16) {
                fclose(stream);
                return fail(number, "coordinates: one letter X, Y or Z per joint (at most 16)");
            }
            for (i = 0; letters[i]; i++) {
                joint_axis[i] = axis_of(letters[i]);
                if (joint_axis[i] < 0) {
                    fclose(stream);
                    return fail(number, "coordinates: only X, Y and Z (trivkins)");
                }
            }
            joint_count = i;
        } else if (strcmp(word, "chain") == 0) {
            /* for the reader: the lever lines carry the chain */
        } else if (strcmp(word, "lever") == 0) {
            if (sscanf(line, "%*s %31s %lf %lf %lf", letters, &a, &b, &c) != 4
                || (k = axis_of(letters[0])) < 0 || letters[1]) {
                fclose(stream);
                return fail(number, "lever: axis letter and three 0/1 flags");
            }
            lever[k][0] = a;
            lever[k][1] = b;
            lever[k][2] = c;
        } else if (strcmp(word, "tool_offset_mm") == 0) {
            if (sscanf(line, "%*s %lf %lf %lf", &a, &b, &c) != 3) {
                fclose(stream);
                return fail(number, "tool_offset_mm: three numbers");
            }
            tool_offset_mm[0] = a;
            tool_offset_mm[1] = b;
            tool_offset_mm[2] = c;
        } else if (strcmp(word, "squareness_urad") == 0) {
            if (sscanf(line, "%*s %lf %lf %lf", &a, &b, &c) != 3) {
                fclose(stream);
                return fail(number, "squareness_urad: EC0Y EA0Z EB0Z");
            }
            squareness_rad[0] = a * 1e-6;
            squareness_rad[1] = b * 1e-6;
            squareness_rad[2] = c * 1e-6;
        } else if (strcmp(word, "max_correction_um") == 0) {
            if (sscanf(line, "%*s %lf", &a) != 1 || !(a > 0)) {
                fclose(stream);
                return fail(number, "max_correction_um: a positive number");
            }
            bound_mm = a * 1e-3;
        } else if (strcmp(word, "table") == 0) {
            if (sscanf(line, "%*s %31s %d", letters, &remaining) != 2
                || find_name(letters, &k, &i) != 0) {
                fclose(stream);
                return fail(number, "table: an ISO 230-1 name (EXX ... ECZ) and a point count");
            }
            if (remaining < 2 || remaining > MAX_POINTS) {
                fclose(stream);
                return fail(number, "table: between 2 and 4096 points");
            }
            if (tables[k][i].count) {
                fclose(stream);
                return fail(number, "table given twice");
            }
            current = &tables[k][i];
            current->count = remaining;
            scale_index = i;
            seen_tables++;
        } else {
            fclose(stream);
            return fail(number, "unknown key");
        }
    }
    fclose(stream);
    if (remaining > 0)
        return fail(number, "the file ends inside a table (truncated)");
    if (!have_crc)
        return fail(number, "no crc32 line at the end (truncated)");
    if (joint_count == 0)
        return fail(number, "no coordinates line");
    if (bound_mm <= 0)
        return fail(number, "no max_correction_um line");
    if (seen_tables != 18)
        return fail(number, "the file must hold all 18 error tables");
    for (k = 0; k < 3; k++) {
        cover_low_mm[k] = -1e300;
        cover_high_mm[k] = 1e300;
        for (i = 0; i < 6; i++) {
            error_table_t *t = &tables[k][i];
            cover_low_mm[k] = fmax(cover_low_mm[k], t->position_mm[0]);
            cover_high_mm[k] = fmin(cover_high_mm[k], t->position_mm[t->count - 1]);
        }
        if (!(cover_low_mm[k] < cover_high_mm[k]))
            return fail(number, "an axis's tables do not overlap");
    }
    return 0;
}

/* Linear interpolation, end values held outside (as numpy.interp). */
static double interpolate(const error_table_t *t, double x) {
    int low = 0, high = t->count - 1;
    if (x <= t->position_mm[0])
        return t->value[0];
    if (x >= t->position_mm[high])
        return t->value[high];
    while (high - low > 1) {
        int middle = (low + high) / 2;
        if (t->position_mm[middle] <= x)
            low = middle;
        else
            high = middle;
    }
    return t->value[low] + (t->value[high] - t->value[low]) * (x - t->position_mm[low])
           / (t->position_mm[high] - t->position_mm[low]);
}

/* dp: deviation of the tool point (actual minus nominal) at CNC coordinates q, mm. */
static void deviation(const double q[3], double dp[3]) {
    int k, j;
    dp[0] = -q[1] * squareness_rad[0] + q[2] * squareness_rad[2];
    dp[1] = -q[2] * squareness_rad[1];
    dp[2] = 0;
    for (k = 0; k < 3; k++) {
        double e[3], r[3];
        for (j = 0; j < 3; j++) {
            dp[j] += interpolate(&tables[k][j], q[k]);
            e[j] = interpolate(&tables[k][3 + j], q[k]);
            r[j] = tool_offset_mm[j] + lever[k][j] * q[j];
        }
        dp[0] += e[1] * r[2] - e[2] * r[1];
        dp[1] += e[2] * r[0] - e[0] * r[2];
        dp[2] += e[0] * r[1] - e[1] * r[0];
    }
}

EXTRA_SETUP() {
    int r;
    static int loaded = 0;
    if (loaded)
        return fail(0, "only one instance (count=1) is supported");
    r = read_table_file();
    if (r)
        return r;
    loaded = 1;
    personality = joint_count;
    rtapi_print_msg(RTAPI_MSG_INFO, "xmalign_volcomp: %s: %d joints\n", table, joint_count);
    return 0;
}

FUNCTION(feedback) {
    int j;
    for (j = 0; j < personality; j++)
        motor_pos_fb_out(j) = motor_pos_fb_in(j) - applied_mm[joint_axis[j]];
}

FUNCTION(command) {
    double k[3] = {0, 0, 0}, goal[3] = {0, 0, 0}, dp[3], q[3], step;
    int seen[3] = {0, 0, 0}, j, a, iteration, code = 0;
    int homed = all_homed;

    /* every joint by its own pin too: is-all-homed reads TRUE before the joints are active */
    for (j = 0; j < personality; j++)
        homed = homed && joint_homed(j);

    for (j = 0; j < personality; j++) {
        a = joint_axis[j];
        if (!seen[a]) {
            k[a] = joint_pos_cmd(j);
            seen[a] = 1;
        }
    }
    if (homed) {
        for (a = 0; a < 3; a++)
            if (seen[a] && (k[a] < cover_low_mm[a] - 1e-6 || k[a] > cover_high_mm[a] + 1e-6))
                code = 1;
        /* c = -dp(k + c): three fixed-point steps (dp's slope is ~1e-4, so ~1e-12 mm) */
        for (iteration = 0; code == 0 && iteration < 3; iteration++) {
            for (a = 0; a < 3; a++)
                q[a] = k[a] + goal[a];
            deviation(q, dp);
            for (a = 0; a < 3; a++)
                goal[a] = -dp[a];
        }
        for (a = 0; code == 0 && a < 3; a++)
            if (fabs(goal[a]) > bound_mm)
                code = 2;
    }
    if (code == 0)
        for (a = 0; a < 3; a++)
            target(a) = goal[a];
    if (motion_enabled && code == 0) {
        step = fabs(max_rate) * fperiod;
        for (a = 0; a < 3; a++) {
            double change = goal[a] - applied_mm[a];
            applied_mm[a] += change > step ? step : (change < -step ? -step : change);
        }
    } else if (!motion_enabled && !homed) {
        /* drives disabled, frame unknown: nothing moves, and homing must start from 0 */
        for (a = 0; a < 3; a++)
            applied_mm[a] = 0;
    }
    for (a = 0; a < 3; a++)
        correction(a) = applied_mm[a];
    for (j = 0; j < personality; j++)
        motor_pos_out(j) = motor_pos_cmd(j) + applied_mm[joint_axis[j]];
    if (reset || !enable_in)
        tripped = 0;
    else if (code != 0 && last_code == 0)
        tripped = 1;
    last_code = code;
    fault = code;
    ok = code == 0;
    active = motion_enabled && homed && code == 0;
    enable_out = enable_in && !tripped;
}
