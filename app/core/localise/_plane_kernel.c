/*
 * The localiser's per-point plane fit (app/core/localise/surface.py, neighbourhood_planes)
 * as compiled loops: gather a neighbourhood, centre it, its covariance and the closed-form
 * eigen-decomposition's (surface.plane_fit) arithmetic, written to the caller's arrays.
 *
 * Optional: setup.py builds it when a C compiler is there (Extension(optional=True)), and
 * surface.py falls back to the numpy passes without it.  The arithmetic is numpy's, operation
 * by operation and in its summation order (the pairwise sum of a row, einsum's two-lane dot
 * products), and the arccos and cosines between the two loops are numpy's own (its vectorised
 * versions differ from the C library's in the last bits), so the results are numpy's to the
 * bit (tests/core/test_plane_kernel.py compares them).
 *
 * No numpy headers: arrays come through the buffer protocol, so building needs only a C
 * compiler and Python's headers.  The loops run without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define UINT32_FORMATS "IL"
#include <math.h>

/* numpy's pairwise sum of n values, as DOUBLE_pairwise_sum does it (blocks of 128). */
static double pairwise_sum(const double *values, Py_ssize_t n)
{
    if (n < 8) {
        double sum = -0.0;
        for (Py_ssize_t i = 0; i < n; i++) {
            sum += values[i];
        }
        return sum;
    }
    if (n > 128) {
        Py_ssize_t half = n / 2;
        half -= half % 8;
        return pairwise_sum(values, half) + pairwise_sum(values + half, n - half);
    }
    double r[8];
    for (int j = 0; j < 8; j++) {
        r[j] = values[j];
    }
    Py_ssize_t i;
    for (i = 8; i < n - (n % 8); i += 8) {
        for (int j = 0; j < 8; j++) {
            r[j] += values[i + j];
        }
    }
    double sum = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
    for (; i < n; i++) {
        sum += values[i];
    }
    return sum;
}

/* numpy's einsum "ck,ck->c" for one row of n values: two lanes, four pairs of them a step. */
static double dot(const double *first, const double *second, Py_ssize_t n)
{
    double lane0 = 0.0, lane1 = 0.0;
    Py_ssize_t i = 0;
    for (; n - i >= 8; i += 8) {
        double even = first[i + 6] * second[i + 6] + lane0;
        double odd = first[i + 7] * second[i + 7] + lane1;
        even = first[i + 4] * second[i + 4] + even;
        odd = first[i + 5] * second[i + 5] + odd;
        even = first[i + 2] * second[i + 2] + even;
        odd = first[i + 3] * second[i + 3] + odd;
        lane0 = first[i] * second[i] + even;
        lane1 = first[i + 1] * second[i + 1] + odd;
    }
    for (; i < n; i += 2) {
        lane0 = first[i] * second[i] + lane0;
        if (i + 1 < n) {
            lane1 = first[i + 1] * second[i + 1] + lane1;
        }
        else {
            lane1 = 0.0 * 0.0 + lane1;
        }
    }
    return lane0 + lane1;
}

typedef struct {
    Py_buffer view;
    int held;
} Held;

static int hold(PyObject *object, Held *held, int flags, const char *name, int ndim,
                const char *formats, Py_ssize_t itemsize)
{
    if (PyObject_GetBuffer(object, &held->view, flags) < 0) {
        return -1;
    }
    held->held = 1;
    const char *format = held->view.format == NULL ? "B" : held->view.format;
    if (format[0] == '<' || format[0] == '=' || format[0] == '@') {
        format++;
    }
    if (held->view.ndim != ndim || strlen(format) != 1 || strchr(formats, format[0]) == NULL ||
        held->view.itemsize != itemsize) {
        PyErr_Format(PyExc_TypeError, "%s: expected a %d-d array of type '%s' (%zd bytes)", name,
                     ndim, formats, itemsize);
        return -1;
    }
    return 0;
}

static void release(Held *held, int count)
{
    for (int i = 0; i < count; i++) {
        if (held[i].held) {
            PyBuffer_Release(&held[i].view);
        }
    }
}


/* The moments' rows (see plane_moments' docstring). */
enum { C00, C11, C22, C01, C02, C12, CX, CY, CZ, MEAN_DIAGONAL, SPREAD, HALF_DETERMINANT, MOMENTS };

static int hold_all(PyObject **objects, Held *held, const char **names, const int *ndims,
                    const char **formats, const Py_ssize_t *itemsizes, const int *flags, int count)
{
    for (int i = 0; i < count; i++) {
        if (hold(objects[i], &held[i], flags[i] | PyBUF_FORMAT, names[i], ndims[i], formats[i],
                 itemsizes[i]) < 0) {
            release(held, count);
            return -1;
        }
    }
    return 0;
}

#define READ PyBUF_C_CONTIGUOUS
#define WRITE (PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE)
#define ROWS_FORMAT "qln"

PyDoc_STRVAR(plane_moments_doc,
             "plane_moments(points, neighbor_index, rows, moments)\n\n"
             "For row i of rows, the neighbourhood neighbor_index[rows[i]] of points: its "
             "covariance (c00, c11, c22, c01, c02, c12), centroid (x, y, z), and plane_fit's "
             "mean diagonal, spread and half determinant, written to moments[:, i].\n"
             "points: (n, 3) float64 (any strides); neighbor_index: (p, k) uint32, C order; "
             "rows: (m,) int64; moments: (12, >= m) float64, C order.");

static PyObject *plane_moments(PyObject *module, PyObject *args)
{
    PyObject *objects[4];
    Held held[4];
    memset(held, 0, sizeof(held));
    if (!PyArg_ParseTuple(args, "OOOO", &objects[0], &objects[1], &objects[2], &objects[3])) {
        return NULL;
    }
    static const char *names[4] = {"points", "neighbor_index", "rows", "moments"};
    static const int ndims[4] = {2, 2, 1, 2};
    static const char *formats[4] = {"d", UINT32_FORMATS, ROWS_FORMAT, "d"};
    static const Py_ssize_t itemsizes[4] = {8, 4, 8, 8};
    static const int flags[4] = {PyBUF_STRIDES, READ, READ, WRITE};
    if (hold_all(objects, held, names, ndims, formats, itemsizes, flags, 4) < 0) {
        return NULL;
    }
    Py_ssize_t n = held[0].view.shape[0];
    Py_ssize_t count = held[1].view.shape[0], columns = held[1].view.shape[1];
    Py_ssize_t row_count = held[2].view.shape[0], width = held[3].view.shape[1];
    if (held[0].view.shape[1] != 3 || columns < 1 || held[3].view.shape[0] != MOMENTS ||
        width < row_count) {
        release(held, 4);
        PyErr_SetString(PyExc_ValueError, "plane_moments: points (n, 3), neighbor_index "
                                          "(p, >= 1), moments (12, >= len(rows))");
        return NULL;
    }
    const char *points = held[0].view.buf;
    Py_ssize_t row_stride = held[0].view.strides[0], column_stride = held[0].view.strides[1];
    const uint32_t *index = held[1].view.buf;
    const int64_t *rows = held[2].view.buf;
    double *moments = held[3].view.buf;
    Py_ssize_t bad_row = -1, bad_index = -1;
    double *buffer = PyMem_RawMalloc(3 * columns * sizeof(double));
    if (buffer == NULL) {
        release(held, 4);
        return PyErr_NoMemory();
    }
    Py_BEGIN_ALLOW_THREADS
    double *deviation[3] = {buffer, buffer + columns, buffer + 2 * columns};
    double k = (double)columns;
    for (Py_ssize_t i = 0; i < row_count && bad_row < 0 && bad_index < 0; i++) {
        int64_t row = rows[i];
        if (row < 0 || row >= count) {
            bad_row = i;
            break;
        }
        const uint32_t *neighbours = index + row * columns;
        for (Py_ssize_t j = 0; j < columns; j++) {
            if ((Py_ssize_t)neighbours[j] >= n) {
                bad_index = i;
                break;
            }
            /* the three coordinates of a neighbour together: one row of points read once */
            const char *point = points + (Py_ssize_t)neighbours[j] * row_stride;
            deviation[0][j] = *(const double *)point;
            deviation[1][j] = *(const double *)(point + column_stride);
            deviation[2][j] = *(const double *)(point + 2 * column_stride);
        }
        if (bad_index >= 0) {
            break;
        }
        for (int axis = 0; axis < 3; axis++) {
            double *values = deviation[axis];
            double mean = pairwise_sum(values, columns) / k;
            moments[(CX + axis) * width + i] = mean;
            for (Py_ssize_t j = 0; j < columns; j++) {
                values[j] -= mean;
            }
        }
        const double *dx = deviation[0], *dy = deviation[1], *dz = deviation[2];
        double c00 = dot(dx, dx, columns) / k, c11 = dot(dy, dy, columns) / k;
        double c22 = dot(dz, dz, columns) / k, c01 = dot(dx, dy, columns) / k;
        double c02 = dot(dx, dz, columns) / k, c12 = dot(dy, dz, columns) / k;
        /* plane_fit up to its arccos, operation by operation */
        double mean_diagonal = (c00 + c11 + c22) / 3.0;
        double d00 = c00 - mean_diagonal, d11 = c11 - mean_diagonal, d22 = c22 - mean_diagonal;
        double spread = sqrt((d00 * d00 + d11 * d11 + d22 * d22) / 6.0 +
                             (c01 * c01 + c02 * c02 + c12 * c12) / 3.0);
        double safe_spread = spread > 0 ? spread : 1.0;
        double b00 = d00 / safe_spread, b11 = d11 / safe_spread, b22 = d22 / safe_spread;
        double b01 = c01 / safe_spread, b02 = c02 / safe_spread, b12 = c12 / safe_spread;
        double half_determinant = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) +
                                   b02 * (b01 * b12 - b11 * b02)) /
                                  2.0;
        double values[MOMENTS] = {c00, c11, c22, c01, c02, c12, 0.0, 0.0, 0.0,
                                  mean_diagonal, spread, half_determinant};
        for (int m = 0; m < MOMENTS; m++) {
            if (m < CX || m > CZ) {
                moments[m * width + i] = values[m];
            }
        }
    }
    Py_END_ALLOW_THREADS
    PyMem_RawFree(buffer);
    release(held, 4);
    if (bad_row >= 0) {
        PyErr_Format(PyExc_IndexError, "plane_moments: rows[%zd] is outside 0..%zd", bad_row,
                     count - 1);
        return NULL;
    }
    if (bad_index >= 0) {
        PyErr_Format(PyExc_IndexError, "plane_moments: a neighbour index is outside 0..%zd", n - 1);
        return NULL;
    }
    Py_RETURN_NONE;
}

PyDoc_STRVAR(plane_finish_doc,
             "plane_finish(moments, cos_largest, cos_smallest, rows, normal, plane_constant, "
             "residual_variance, middle_over_largest, variation)\n\n"
             "plane_fit after its cosines, and neighbourhood_planes' outputs, for the moments "
             "of plane_moments: column i is written to the outputs' row rows[i].\n"
             "moments: (12, >= m) float64; cos_largest, cos_smallest: (>= m,) float64 (numpy's "
             "cos of the angle and of the angle + 2 pi / 3); rows: (m,) int64; normal: (p, 3) "
             "float32; the others (p,) float64; all C order.");

static PyObject *plane_finish(PyObject *module, PyObject *args)
{
    enum { MOMENT_ARRAY, COS_LARGEST, COS_SMALLEST, ROWS, NORMAL, CONSTANT, RESIDUAL, RATIO,
           VARIATION, ARRAYS };
    PyObject *objects[ARRAYS];
    Held held[ARRAYS];
    memset(held, 0, sizeof(held));
    if (!PyArg_ParseTuple(args, "OOOOOOOOO", &objects[0], &objects[1], &objects[2], &objects[3],
                          &objects[4], &objects[5], &objects[6], &objects[7], &objects[8])) {
        return NULL;
    }
    static const char *names[ARRAYS] = {"moments", "cos_largest", "cos_smallest", "rows",
                                        "normal", "plane_constant", "residual_variance",
                                        "middle_over_largest", "variation"};
    static const int ndims[ARRAYS] = {2, 1, 1, 1, 2, 1, 1, 1, 1};
    static const char *formats[ARRAYS] = {"d", "d", "d", ROWS_FORMAT, "f", "d", "d", "d", "d"};
    static const Py_ssize_t itemsizes[ARRAYS] = {8, 8, 8, 8, 4, 8, 8, 8, 8};
    static const int flags[ARRAYS] = {READ, READ, READ, READ, WRITE, WRITE, WRITE, WRITE, WRITE};
    if (hold_all(objects, held, names, ndims, formats, itemsizes, flags, ARRAYS) < 0) {
        return NULL;
    }
    Py_ssize_t row_count = held[ROWS].view.shape[0], width = held[MOMENT_ARRAY].view.shape[1];
    Py_ssize_t count = held[NORMAL].view.shape[0];
    int shapes_agree = held[MOMENT_ARRAY].view.shape[0] == MOMENTS && width >= row_count &&
                       held[COS_LARGEST].view.shape[0] >= row_count &&
                       held[COS_SMALLEST].view.shape[0] >= row_count &&
                       held[NORMAL].view.shape[1] == 3;
    for (int i = CONSTANT; i < ARRAYS; i++) {
        shapes_agree = shapes_agree && held[i].view.shape[0] == count;
    }
    if (!shapes_agree) {
        release(held, ARRAYS);
        PyErr_SetString(PyExc_ValueError, "plane_finish: moments (12, >= m), cosines (>= m,), "
                                          "normal (p, 3) and outputs of p rows");
        return NULL;
    }
    const double *moments = held[MOMENT_ARRAY].view.buf;
    const double *cos_largest = held[COS_LARGEST].view.buf;
    const double *cos_smallest = held[COS_SMALLEST].view.buf;
    const int64_t *rows = held[ROWS].view.buf;
    float *normal = held[NORMAL].view.buf;
    double *plane_constant = held[CONSTANT].view.buf, *residual = held[RESIDUAL].view.buf;
    double *ratio = held[RATIO].view.buf, *variation = held[VARIATION].view.buf;
    Py_ssize_t bad_row = -1;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < row_count; i++) {
        int64_t row = rows[i];
        if (row < 0 || row >= count) {
            bad_row = i;
            break;
        }
        double c00 = moments[C00 * width + i], c11 = moments[C11 * width + i];
        double c22 = moments[C22 * width + i], c01 = moments[C01 * width + i];
        double c02 = moments[C02 * width + i], c12 = moments[C12 * width + i];
        double mean_diagonal = moments[MEAN_DIAGONAL * width + i];
        double spread = moments[SPREAD * width + i];
        double largest = mean_diagonal + 2.0 * spread * cos_largest[i];
        double smallest = mean_diagonal + 2.0 * spread * cos_smallest[i];
        double s00 = c00 - smallest, s11 = c11 - smallest, s22 = c22 - smallest;
        double candidates[3][3] = {
            {c01 * c12 - c02 * s11, c02 * c01 - s00 * c12, s00 * s11 - c01 * c01},
            {c01 * s22 - c02 * c12, c02 * c02 - s00 * s22, s00 * c12 - c01 * c02},
            {s11 * s22 - c12 * c12, c12 * c02 - c01 * s22, c01 * c12 - s11 * c02},
        };
        double best[3] = {0.0, 0.0, 0.0};
        double best_norm_squared = -1.0;
        for (int c = 0; c < 3; c++) {
            double x = candidates[c][0], y = candidates[c][1], z = candidates[c][2];
            double norm_squared = x * x + y * y + z * z;
            if (norm_squared > best_norm_squared) {
                best[0] = x;
                best[1] = y;
                best[2] = z;
                best_norm_squared = norm_squared;
            }
        }
        double best_norm = sqrt(best_norm_squared);
        double divisor = best_norm > 0 ? best_norm : 1.0;
        float *unit = normal + row * 3;
        for (int axis = 0; axis < 3; axis++) {
            unit[axis] = (float)(best[axis] / divisor);
        }
        if (best_norm <= 0 || spread <= 0) {
            unit[0] = 0.0f;
            unit[1] = 0.0f;
            unit[2] = 1.0f;
        }
        smallest = smallest > 0.0 ? smallest : 0.0;
        /* einsum "cd,cd->c" over the three coordinates: two lanes (x, z) and (y) */
        double lane0 = moments[CX * width + i] * (double)unit[0] + 0.0;
        double lane1 = moments[CY * width + i] * (double)unit[1] + 0.0;
        lane0 = moments[CZ * width + i] * (double)unit[2] + lane0;
        lane1 = 0.0 * 0.0 + lane1;
        plane_constant[row] = lane0 + lane1;
        double trace = c00 + c11 + c22;
        double middle = trace - smallest - largest;
        ratio[row] = middle / (largest > 1e-300 ? largest : 1e-300);
        variation[row] = smallest / (trace > 1e-300 ? trace : 1e-300);
        residual[row] = smallest;
    }
    Py_END_ALLOW_THREADS
    release(held, ARRAYS);
    if (bad_row >= 0) {
        PyErr_Format(PyExc_IndexError, "plane_finish: rows[%zd] is outside 0..%zd", bad_row,
                     count - 1);
        return NULL;
    }
    Py_RETURN_NONE;
}


PyDoc_STRVAR(neighbourhood_means_doc,
             "neighbourhood_means(values, neighbor_index, rows, means)\n\n"
             "means[rows[i]] = values[neighbor_index[rows[i]]].mean() in numpy's summation "
             "order.\n"
             "values: (n,) float64; neighbor_index: (p, k) uint32; rows: (m,) int64; means: "
             "(p,) float64; all C order.");

static PyObject *neighbourhood_means(PyObject *module, PyObject *args)
{
    PyObject *objects[4];
    Held held[4];
    memset(held, 0, sizeof(held));
    if (!PyArg_ParseTuple(args, "OOOO", &objects[0], &objects[1], &objects[2], &objects[3])) {
        return NULL;
    }
    static const char *names[4] = {"values", "neighbor_index", "rows", "means"};
    static const int ndims[4] = {1, 2, 1, 1};
    static const char *formats[4] = {"d", UINT32_FORMATS, ROWS_FORMAT, "d"};
    static const Py_ssize_t itemsizes[4] = {8, 4, 8, 8};
    static const int flags[4] = {READ, READ, READ, WRITE};
    if (hold_all(objects, held, names, ndims, formats, itemsizes, flags, 4) < 0) {
        return NULL;
    }
    Py_ssize_t n = held[0].view.shape[0];
    Py_ssize_t count = held[1].view.shape[0], columns = held[1].view.shape[1];
    Py_ssize_t row_count = held[2].view.shape[0];
    if (columns < 1 || held[3].view.shape[0] != count) {
        release(held, 4);
        PyErr_SetString(PyExc_ValueError, "neighbourhood_means: neighbor_index (p, >= 1), "
                                          "means (p,)");
        return NULL;
    }
    const double *values = held[0].view.buf;
    const uint32_t *index = held[1].view.buf;
    const int64_t *rows = held[2].view.buf;
    double *means = held[3].view.buf;
    Py_ssize_t bad_row = -1, bad_index = -1;
    double *gathered = PyMem_RawMalloc(columns * sizeof(double));
    if (gathered == NULL) {
        release(held, 4);
        return PyErr_NoMemory();
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < row_count && bad_index < 0; i++) {
        int64_t row = rows[i];
        if (row < 0 || row >= count) {
            bad_row = i;
            break;
        }
        const uint32_t *neighbours = index + row * columns;
        for (Py_ssize_t j = 0; j < columns; j++) {
            if ((Py_ssize_t)neighbours[j] >= n) {
                bad_index = i;
                break;
            }
            gathered[j] = values[neighbours[j]];
        }
        if (bad_index < 0) {
            means[row] = pairwise_sum(gathered, columns) / (double)columns;
        }
    }
    Py_END_ALLOW_THREADS
    PyMem_RawFree(gathered);
    release(held, 4);
    if (bad_row >= 0) {
        PyErr_Format(PyExc_IndexError, "neighbourhood_means: rows[%zd] is outside 0..%zd",
                     bad_row, count - 1);
        return NULL;
    }
    if (bad_index >= 0) {
        PyErr_Format(PyExc_IndexError, "neighbourhood_means: a neighbour index is outside 0..%zd",
                     n - 1);
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"plane_moments", plane_moments, METH_VARARGS, plane_moments_doc},
    {"plane_finish", plane_finish, METH_VARARGS, plane_finish_doc},
    {"neighbourhood_means", neighbourhood_means, METH_VARARGS, neighbourhood_means_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_plane_kernel",
    "The localiser's plane fit as compiled loops (see surface.neighbourhood_planes).", -1, methods,
};

PyMODINIT_FUNC PyInit__plane_kernel(void)
{
    return PyModule_Create(&module);
}
