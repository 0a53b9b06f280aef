/* The SITL's state derivative compiled: sitl.dynamics.make_derivative's closure with sitl.fused_wrench's
 * airframe wrench inlined, the same arithmetic in the same order (built with -ffp-contract=off, so no fused
 * multiply-adds), hence bit-identical results. tests/test_compiled_derivative.py holds it to the Python
 * derivative with == at many random states; sitl/compiled_physics.py packs the constants.
 *
 * derivative(constants: bytes, wind: list[3], s: 17 floats, cmd: 4 floats) -> tuple of 17 floats
 *   constants: struct.pack of the doubles of `Constants` below, in order (sitl.compiled_physics.LAYOUT)
 *   wind: NED m/s, read at every call (the Python list the Quadrotor updates each exchange step)
 *   s: position NED m, velocity NED m/s, quaternion body->earth (w, x, y, z), rates FRD rad/s, rotor speeds
 *      rad/s; cmd: commanded rotor speeds rad/s
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

typedef struct {
    double version;  /* LAYOUT_VERSION: a stale build is refused, not misread */
    double paper;    /* 1: the paper's closed form; 0: the fused airframe wrench */
    double itm, g, im;
    double j[9], ji[9];
    double d0, d1, d2;
    /* the paper's closed form (sitl.mixer.QuadXMixer, per-axis body drag) */
    double ct, k, cm, jm, cdx, cdy, cdz, has_body_drag;
    /* the fused airframe wrench (sitl.fused_wrench) */
    double ct1, ct2, ct3, ct4;
    double x1, y1, z1, x2, y2, z2, x3, y3, z3, x4, y4, z4;
    double q1, q2, q3, q4, j1, j2, j3, j4;
    double has_drag, kd, kz, has_lift, kh, has_ground, rr, hmin, has_frame, cx, cy, cz, dx, dy, dz, need_air;
} Constants;

#define LAYOUT_VERSION 1.0

static int read_doubles(PyObject *seq, double *out, Py_ssize_t n, const char *what) {
    PyObject **items;
    Py_ssize_t len;
    if (PyList_CheckExact(seq)) {
        items = ((PyListObject *)seq)->ob_item;
        len = PyList_GET_SIZE(seq);
    } else if (PyTuple_CheckExact(seq)) {
        items = ((PyTupleObject *)seq)->ob_item;
        len = PyTuple_GET_SIZE(seq);
    } else {
        PyObject *fast = PySequence_Fast(seq, what);
        if (fast == NULL) return -1;
        int rc = read_doubles(fast, out, n, what);
        Py_DECREF(fast);
        return rc;
    }
    if (len != n) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd floats, got %zd", what, n, len);
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *o = items[i];
        if (PyFloat_CheckExact(o)) {
            out[i] = PyFloat_AS_DOUBLE(o);
        } else {
            out[i] = PyFloat_AsDouble(o);
            if (out[i] == -1.0 && PyErr_Occurred()) return -1;
        }
    }
    return 0;
}

static PyObject *derivative(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "derivative(constants, wind, s, cmd) takes 4 arguments");
        return NULL;
    }
    if (!PyBytes_Check(args[0]) || PyBytes_GET_SIZE(args[0]) != (Py_ssize_t)sizeof(Constants)) {
        PyErr_Format(PyExc_ValueError, "constants: expected %zd bytes", (Py_ssize_t)sizeof(Constants));
        return NULL;
    }
    Constants c;
    memcpy(&c, PyBytes_AS_STRING(args[0]), sizeof(Constants));
    if (c.version != LAYOUT_VERSION) {
        PyErr_SetString(PyExc_ValueError, "constants: layout version mismatch (rebuild the extension)");
        return NULL;
    }
    double wind[3], s[17], cmd[4];
    if (read_doubles(args[1], wind, 3, "wind") < 0 || read_doubles(args[2], s, 17, "state") < 0
        || read_doubles(args[3], cmd, 4, "cmd") < 0)
        return NULL;

    const double z = s[2], vx = s[3], vy = s[4], vz = s[5];
    const double qw = s[6], qx = s[7], qy = s[8], qz = s[9];
    const double wx = s[10], wy = s[11], wz = s[12];
    const double w1 = s[13], w2 = s[14], w3 = s[15], w4 = s[16];
    const double itm = c.itm;
    const double dw1 = (cmd[0] - w1) * itm, dw2 = (cmd[1] - w2) * itm;
    const double dw3 = (cmd[2] - w3) * itm, dw4 = (cmd[3] - w4) * itm;
    /* rotation body -> earth */
    const double xx = qx * qx, yy = qy * qy, zz = qz * qz;
    const double xy = qx * qy, xz = qx * qz, yz = qy * qz;
    const double wxq = qw * qx, wyq = qw * qy, wzq = qw * qz;
    const double r00 = 1.0 - 2.0 * (yy + zz), r01 = 2.0 * (xy - wzq), r02 = 2.0 * (xz + wyq);
    const double r10 = 2.0 * (xy + wzq), r11 = 1.0 - 2.0 * (xx + zz), r12 = 2.0 * (yz - wxq);
    const double r20 = 2.0 * (xz - wyq), r21 = 2.0 * (yz + wxq), r22 = 1.0 - 2.0 * (xx + yy);
    double fbx, fby, fbz, tx, ty, tz, hz;

    if (c.paper == 0.0) { /* sitl.fused_wrench.fused_airframe_wrench */
        const double ex = vx - wind[0], ey = vy - wind[1], ez = vz - wind[2];
        const double ux = r00 * ex + r10 * ey + r20 * ez;
        const double uy = r01 * ex + r11 * ey + r21 * ez;
        const double uz = r02 * ex + r12 * ey + r22 * ez;
        double t1 = c.ct1 * w1 * w1, t2 = c.ct2 * w2 * w2, t3 = c.ct3 * w3 * w3, t4 = c.ct4 * w4 * w4;
        const double x1 = c.x1, y1 = c.y1, z1 = c.z1, x2 = c.x2, y2 = c.y2, z2 = c.z2;
        const double x3 = c.x3, y3 = c.y3, z3 = c.z3, x4 = c.x4, y4 = c.y4, z4 = c.z4;
        double a1x = 0, a1y = 0, a1z = 0, a2x = 0, a2y = 0, a2z = 0;
        double a3x = 0, a3y = 0, a3z = 0, a4x = 0, a4y = 0, a4z = 0;
        if (c.need_air != 0.0) {
            a1x = ux + wy * z1 - wz * y1; a1y = uy + wz * x1 - wx * z1; a1z = uz + wx * y1 - wy * x1;
            a2x = ux + wy * z2 - wz * y2; a2y = uy + wz * x2 - wx * z2; a2z = uz + wx * y2 - wy * x2;
            a3x = ux + wy * z3 - wz * y3; a3y = uy + wz * x3 - wx * z3; a3z = uz + wx * y3 - wy * x3;
            a4x = ux + wy * z4 - wz * y4; a4y = uy + wz * x4 - wx * z4; a4z = uz + wx * y4 - wy * x4;
            if (c.has_lift != 0.0) {
                const double kh = c.kh;
                t1 = t1 + kh * (a1x * a1x + a1y * a1y);
                t2 = t2 + kh * (a2x * a2x + a2y * a2y);
                t3 = t3 + kh * (a3x * a3x + a3y * a3y);
                t4 = t4 + kh * (a4x * a4x + a4y * a4y);
            }
        }
        if (c.has_ground != 0.0) {
            const double rr = c.rr, hmin = c.hmin;
            double h1 = -(z + r20 * x1 + r21 * y1 + r22 * z1);
            double h2 = -(z + r20 * x2 + r21 * y2 + r22 * z2);
            double h3 = -(z + r20 * x3 + r21 * y3 + r22 * z3);
            double h4 = -(z + r20 * x4 + r21 * y4 + r22 * z4);
            h1 = h1 > hmin ? h1 : hmin;
            h2 = h2 > hmin ? h2 : hmin;
            h3 = h3 > hmin ? h3 : hmin;
            h4 = h4 > hmin ? h4 : hmin;
            t1 = t1 * (1.0 / (1.0 - rr / (h1 * h1)));
            t2 = t2 * (1.0 / (1.0 - rr / (h2 * h2)));
            t3 = t3 * (1.0 / (1.0 - rr / (h3 * h3)));
            t4 = t4 * (1.0 / (1.0 - rr / (h4 * h4)));
        }
        fbz = -(t1 + t2 + t3 + t4);
        tx = -(y1 * t1 + y2 * t2 + y3 * t3 + y4 * t4);
        ty = x1 * t1 + x2 * t2 + x3 * t3 + x4 * t4;
        tz = c.q1 * w1 * w1 + c.q2 * w2 * w2 + c.q3 * w3 * w3 + c.q4 * w4 * w4;
        hz = c.j1 * w1 + c.j2 * w2 + c.j3 * w3 + c.j4 * w4;
        fbx = fby = 0.0;
        if (c.has_drag != 0.0) {
            const double kd = c.kd, kz = c.kz;
            const double d1 = -w1 * kd, d2 = -w2 * kd, d3 = -w3 * kd, d4 = -w4 * kd;
            const double fx1 = d1 * a1x, fy1 = d1 * a1y, fz1 = -w1 * kz * a1z;
            const double fx2 = d2 * a2x, fy2 = d2 * a2y, fz2 = -w2 * kz * a2z;
            const double fx3 = d3 * a3x, fy3 = d3 * a3y, fz3 = -w3 * kz * a3z;
            const double fx4 = d4 * a4x, fy4 = d4 * a4y, fz4 = -w4 * kz * a4z;
            fbx = fx1 + fx2 + fx3 + fx4;
            fby = fy1 + fy2 + fy3 + fy4;
            fbz += fz1 + fz2 + fz3 + fz4;
            tx += ((y1 * fz1 - z1 * fy1) + (y2 * fz2 - z2 * fy2) + (y3 * fz3 - z3 * fy3)
                   + (y4 * fz4 - z4 * fy4));
            ty += ((z1 * fx1 - x1 * fz1) + (z2 * fx2 - x2 * fz2) + (z3 * fx3 - x3 * fz3)
                   + (z4 * fx4 - x4 * fz4));
            tz += ((x1 * fy1 - y1 * fx1) + (x2 * fy2 - y2 * fx2) + (x3 * fy3 - y3 * fx3)
                   + (x4 * fy4 - y4 * fx4));
        }
        if (c.has_frame != 0.0) {
            const double speed = sqrt(ux * ux + uy * uy + uz * uz);
            fbx += -(speed * c.cx + c.dx * (ux > 0.0 ? ux : -ux)) * ux;
            fby += -(speed * c.cy + c.dy * (uy > 0.0 ? uy : -uy)) * uy;
            fbz += -(speed * c.cz + c.dz * (uz > 0.0 ? uz : -uz)) * uz;
        }
    } else { /* the paper's closed form (sitl.dynamics.make_derivative) */
        const double s1 = w1 * w1, s2 = w2 * w2, s3 = w3 * w3, s4 = w4 * w4;
        const double thrust = c.ct * (s1 + s2 + s3 + s4);
        tx = c.k * (-s1 + s2 + s3 - s4);
        ty = c.k * (s1 - s2 + s3 - s4);
        tz = c.cm * (s1 + s2 - s3 - s4);
        hz = c.jm * (-w1 - w2 + w3 + w4);
        fbz = -thrust;
        if (c.has_body_drag != 0.0) {
            const double ubx = r00 * vx + r10 * vy + r20 * vz;
            const double uby = r01 * vx + r11 * vy + r21 * vz;
            const double ubz = r02 * vx + r12 * vy + r22 * vz;
            fbx = -c.cdx * ubx * fabs(ubx);
            fby = -c.cdy * uby * fabs(uby);
            fbz -= c.cdz * ubz * fabs(ubz);
        } else {
            fbx = fby = 0.0;
        }
    }
    const double im = c.im;
    const double ax = (r00 * fbx + r01 * fby + r02 * fbz) * im;
    const double ay = (r10 * fbx + r11 * fby + r12 * fbz) * im;
    const double az = (r20 * fbx + r21 * fby + r22 * fbz) * im + c.g;
    const double dqw = 0.5 * (-qx * wx - qy * wy - qz * wz);
    const double dqx = 0.5 * (qw * wx + qy * wz - qz * wy);
    const double dqy = 0.5 * (qw * wy - qx * wz + qz * wx);
    const double dqz = 0.5 * (qw * wz + qx * wy - qy * wx);
    const double *j = c.j, *ji = c.ji;
    const double hx = j[0] * wx + j[1] * wy + j[2] * wz;
    const double hy = j[3] * wx + j[4] * wy + j[5] * wz;
    const double hzb = j[6] * wx + j[7] * wy + j[8] * wz + hz;
    const double mx = tx - (wy * hzb - wz * hy) - c.d0 * wx;
    const double my = ty - (wz * hx - wx * hzb) - c.d1 * wy;
    const double mz = tz - (wx * hy - wy * hx) - c.d2 * wz;
    const double out[17] = {
        vx, vy, vz, ax, ay, az, dqw, dqx, dqy, dqz,
        ji[0] * mx + ji[1] * my + ji[2] * mz,
        ji[3] * mx + ji[4] * my + ji[5] * mz,
        ji[6] * mx + ji[7] * my + ji[8] * mz,
        dw1, dw2, dw3, dw4,
    };
    PyObject *result = PyTuple_New(17);
    if (result == NULL) return NULL;
    for (int i = 0; i < 17; i++) {
        PyObject *f = PyFloat_FromDouble(out[i]);
        if (f == NULL) {
            Py_DECREF(result);
            return NULL;
        }
        PyTuple_SET_ITEM(result, i, f);
    }
    return result;
}

static PyMethodDef methods[] = {
    {"derivative", (PyCFunction)(void (*)(void))derivative, METH_FASTCALL,
     "derivative(constants, wind, s, cmd) -> the 17-float state derivative (sitl.dynamics' units)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_derivative",
    "The SITL's state derivative, compiled (see sitl.compiled_physics).", -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__derivative(void) {
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    if (PyModule_AddObject(m, "CONSTANTS_SIZE", PyLong_FromSsize_t((Py_ssize_t)sizeof(Constants))) < 0
        || PyModule_AddObject(m, "LAYOUT_VERSION", PyFloat_FromDouble(LAYOUT_VERSION)) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
