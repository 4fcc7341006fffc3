/*
 * Every point's k nearest neighbours in its own cloud (app/core/localise/neighbourhoods.py),
 * found a leaf of points at a time without the GIL.
 *
 * A k-d tree of its own (sliding-midpoint splits, tight boxes, up to LEAF_SIZE points a leaf,
 * coordinates copied in tree order, one array per axis) is searched once per leaf: the leaf's
 * points share one walk of the tree, which skips a node when the gap between its box and the
 * leaf's exceeds the largest k-th distance the leaf's points have found so far, and each point
 * scans the points of a reached leaf when its own gap to that leaf's box is smaller than its own
 * k-th distance.  Squared distances are pykdtree's to the bit: (dx dx + dy dy) + dz dz with no
 * fused multiply-adds (setup.py builds with -ffp-contract=off), so the neighbours and the k-th
 * distance are the same numbers, in the same order, whenever that order is unique.  When it is
 * not (two of the k + 1 nearest at the same distance, e.g. duplicate points), the point is
 * flagged and the caller asks pykdtree for it, whose order among equals follows its own walk.
 *
 * The same walk gives each point of one cloud its nearest point in another (nearest_other: the
 * leaves of the first cloud's tree, the second's tree walked; one nearest kept, a point with
 * two equally near flagged for pykdtree), as pykdtree's k = 1 query gives it.
 *
 * Optional: setup.py builds it when a C compiler is there (Extension(optional=True)); without it
 * neighbourhoods.py queries pykdtree a chunk at a time.  No numpy headers: arrays come through
 * the buffer protocol.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define LEAF_SIZE 32
#define MAX_NEIGHBOURS 256
#define MAX_LEAF 4096 /* larger leaves (many equal points) are left to pykdtree */

typedef struct {
    double low[3], high[3];
    uint32_t start, count;
    int32_t left, right; /* children, or -1 for a leaf */
} Node;

typedef struct {
    Py_ssize_t n;
    double *axis[3]; /* coordinates in tree order */
    uint32_t *row;   /* tree position -> row of the caller's array */
    Node *nodes;
    Py_ssize_t n_nodes, capacity;
    int32_t *leaves; /* leaf nodes in tree order */
    Py_ssize_t n_leaves;
    int depth;
    uint32_t largest_leaf;
} Tree;

static void free_tree(Tree *tree)
{
    for (int d = 0; d < 3; d++) {
        free(tree->axis[d]);
    }
    free(tree->row);
    free(tree->nodes);
    free(tree->leaves);
    memset(tree, 0, sizeof(Tree));
}

static int32_t new_node(Tree *tree)
{
    if (tree->n_nodes == tree->capacity) {
        Py_ssize_t capacity = tree->capacity ? 2 * tree->capacity : 1024;
        Node *grown = realloc(tree->nodes, (size_t)capacity * sizeof(Node));
        if (grown == NULL) {
            return -1;
        }
        tree->nodes = grown;
        tree->capacity = capacity;
    }
    return (int32_t)tree->n_nodes++;
}

static void swap_rows(Tree *tree, uint32_t a, uint32_t b)
{
    for (int d = 0; d < 3; d++) {
        double value = tree->axis[d][a];
        tree->axis[d][a] = tree->axis[d][b];
        tree->axis[d][b] = value;
    }
    uint32_t row = tree->row[a];
    tree->row[a] = tree->row[b];
    tree->row[b] = row;
}

/* The node over tree positions [start, start + count), its subtree built; its id or -1. */
static int32_t build(Tree *tree, uint32_t start, uint32_t count, int depth)
{
    int32_t id = new_node(tree);
    if (id < 0) {
        return -1;
    }
    Node node = {.start = start, .count = count, .left = -1, .right = -1};
    for (int d = 0; d < 3; d++) {
        const double *values = tree->axis[d] + start;
        double low = values[0], high = values[0];
        for (uint32_t i = 1; i < count; i++) {
            if (values[i] < low) {
                low = values[i];
            }
            else if (values[i] > high) {
                high = values[i];
            }
        }
        node.low[d] = low;
        node.high[d] = high;
    }
    if (depth > tree->depth) {
        tree->depth = depth;
    }
    int dim = 0;
    for (int d = 1; d < 3; d++) {
        if (node.high[d] - node.low[d] > node.high[dim] - node.low[dim]) {
            dim = d;
        }
    }
    double split = node.low[dim] + 0.5 * (node.high[dim] - node.low[dim]);
    if (count > LEAF_SIZE && split > node.low[dim]) {
        const double *values = tree->axis[dim];
        int64_t first = start, last = (int64_t)start + count - 1;
        while (first <= last) {
            if (values[first] < split) {
                first++;
            }
            else if (values[last] >= split) {
                last--;
            }
            else {
                swap_rows(tree, (uint32_t)first, (uint32_t)last);
                first++;
                last--;
            }
        }
        /* >= 1 (the lowest value is below split) and < count (the highest is not) */
        uint32_t below = (uint32_t)(first - start);
        int32_t left = build(tree, start, below, depth + 1);
        int32_t right = left < 0 ? -1 : build(tree, start + below, count - below, depth + 1);
        if (right < 0) {
            return -1;
        }
        node.left = left;
        node.right = right;
    }
    else if (count > tree->largest_leaf) {
        tree->largest_leaf = count;
    }
    tree->nodes[id] = node;
    return id;
}

static void collect_leaves(Tree *tree, int32_t id)
{
    const Node *node = &tree->nodes[id];
    if (node->left < 0) {
        tree->leaves[tree->n_leaves++] = id;
        return;
    }
    collect_leaves(tree, node->left);
    collect_leaves(tree, node->right);
}

/* Squared gap between two boxes (0 where they overlap along an axis). */
static inline double box_gap(const Node *a, const Node *b)
{
    double sum = 0.0;
    for (int d = 0; d < 3; d++) {
        double gap = 0.0;
        if (b->high[d] < a->low[d]) {
            gap = a->low[d] - b->high[d];
        }
        else if (b->low[d] > a->high[d]) {
            gap = b->low[d] - a->high[d];
        }
        sum += gap * gap;
    }
    return sum;
}

/* Squared gap between a point and a box: no more than the squared distance (as computed
   below) to any point in the box, rounding being monotonic. */
static inline double point_gap(const double *point, const Node *box)
{
    double sum = 0.0;
    for (int d = 0; d < 3; d++) {
        double gap = 0.0;
        if (point[d] < box->low[d]) {
            gap = box->low[d] - point[d];
        }
        else if (point[d] > box->high[d]) {
            gap = point[d] - box->high[d];
        }
        sum += gap * gap;
    }
    return sum;
}

typedef struct {
    int32_t *stack;
    double *best;      /* (leaf points, k1) squared distances, ascending */
    uint32_t *best_at; /* their tree positions */
    uint8_t *equal;    /* (leaf points,) 1: a point not kept is as far as the k1-th */
    double *scratch;   /* one leaf's squared distances to one point */
    uint32_t *passing; /* the places in that leaf of those no farther than the point's k1-th */
} Work;

/* The squared distances from point to each of a leaf's count points (axis arrays xs, ys, zs), in
   scratch: the same arithmetic (x^2 + y^2, then + z^2) wherever a distance is compared. */
static inline void leaf_squared(const double *xs, const double *ys, const double *zs,
                                uint32_t count, const double point[3], double *scratch)
{
    for (uint32_t j = 0; j < count; j++) {
        double dx = xs[j] - point[0], dy = ys[j] - point[1], dz = zs[j] - point[2];
        double squared = dx * dx + dy * dy;
        scratch[j] = squared + dz * dz;
    }
}

/* One candidate (squared distance, tree position at) offered to a full list of k1 (best,
   best_at, ascending) whose k1-th is *limit: kept in order when nearer, pushing the k1-th out;
   *equal set when one as far as the k1-th is not kept, cleared when the k1-th gets nearer. */
static inline void offer(double *best, uint32_t *best_at, int k1, double squared, uint32_t at,
                         double *limit, uint8_t *equal)
{
    if (squared < *limit) {
        int slot = k1 - 1;
        while (slot > 0 && best[slot - 1] > squared) {
            best[slot] = best[slot - 1];
            best_at[slot] = best_at[slot - 1];
            slot--;
        }
        best[slot] = squared;
        best_at[slot] = at;
        /* the one pushed out was at the old limit */
        *equal = !(best[k1 - 1] < *limit);
        *limit = best[k1 - 1];
    }
    else if (squared == *limit) {
        *equal = 1;
    }
}

/* One reached leaf scanned for each of the own leaf's points that may find a neighbour in it.
   A point's k1 nearest so far are kept; one as far as the k1-th but not kept (seen, or pushed
   out by a nearer one while another as far stays) sets its equal flag, which a nearer k1-th
   clears.  So no point as far as the k1-th is skipped (a leaf is skipped only when its gap is
   larger), and at the end the flag says whether the k1 + 1-th is as far as the k1-th. */
static void scan_leaf(const Tree *own_tree, const Node *own, const Tree *tree, const Node *node,
                      int k1, Work *work)
{
    const double *xs = tree->axis[0] + node->start;
    const double *ys = tree->axis[1] + node->start;
    const double *zs = tree->axis[2] + node->start;
    for (uint32_t i = 0; i < own->count; i++) {
        uint32_t at = own->start + i;
        double point[3] = {own_tree->axis[0][at], own_tree->axis[1][at], own_tree->axis[2][at]};
        double *best = work->best + (size_t)i * k1;
        uint32_t *best_at = work->best_at + (size_t)i * k1;
        double limit = best[k1 - 1];
        if (point_gap(point, node) > limit) {
            continue;
        }
        if (k1 == 1) { /* the nearest only: no list to keep */
            uint8_t equal = work->equal[i];
            uint32_t nearest = best_at[0];
            for (uint32_t j = 0; j < node->count; j++) {
                double dx = xs[j] - point[0], dy = ys[j] - point[1], dz = zs[j] - point[2];
                double squared = dx * dx + dy * dy;
                squared = squared + dz * dz;
                if (squared <= limit) {
                    equal = squared == limit;
                    if (squared < limit) {
                        limit = squared;
                        nearest = node->start + j;
                    }
                }
            }
            best[0] = limit;
            best_at[0] = nearest;
            work->equal[i] = equal;
            continue;
        }
        leaf_squared(xs, ys, zs, node->count, point, work->scratch);
        /* those no farther than the limit listed without a branch (most are farther) */
        uint32_t passed = 0;
        for (uint32_t j = 0; j < node->count; j++) {
            work->passing[passed] = j;
            passed += work->scratch[j] <= limit;
        }
        uint8_t equal = work->equal[i];
        for (uint32_t candidate = 0; candidate < passed; candidate++) {
            uint32_t j = work->passing[candidate];
            offer(best, best_at, k1, work->scratch[j], node->start + j, &limit, &equal);
        }
        work->equal[i] = equal;
    }
}

#define OWN_LEAF_GUESS 1.5 /* times the point before's k1-th squared distance (see below) */

/* Point i's k1-th squared distance is at most (r + d)^2, r the k1-th distance point i - 1 found
   in the leaf (k1 points of the leaf within r of it) and d the distance between the two, rounded
   up: a margin well above the few ulps of the squared distances' rounding. */
static inline double leaf_bound(double previous_kth, double squared_step)
{
    double reach = sqrt(previous_kth) + sqrt(squared_step);
    return reach * reach * (1.0 + 1e-9) + 1e-300;
}

/* The own leaf scanned first, when every point's list is still empty: the same lists and flags
   as scan_leaf gives them, with less work.  The first k1 candidates fill the list from its
   filled end (no shifting of the empty slots), and only the candidates no farther than a bound
   are taken: when at least k1 of the leaf's points are within it, its k1 nearest are, and the
   others are farther than the final k1-th (scan_leaf would have pushed them out again, or never
   taken them, and they set no equal flag).  Any bound is exact by that count; the bound only
   decides the work: first OWN_LEAF_GUESS times the k1-th of the point before (neighbouring
   points of a leaf have about the same spacing; most points take it), else leaf_bound (k1
   within it whenever the point before found k1 in the leaf), else every point of the leaf. */
static void scan_own_leaf(const Tree *tree, const Node *own, int k1, Work *work)
{
    const double *xs = tree->axis[0] + own->start;
    const double *ys = tree->axis[1] + own->start;
    const double *zs = tree->axis[2] + own->start;
    for (uint32_t i = 0; i < own->count; i++) {
        double point[3] = {xs[i], ys[i], zs[i]};
        double *best = work->best + (size_t)i * k1;
        uint32_t *best_at = work->best_at + (size_t)i * k1;
        leaf_squared(xs, ys, zs, own->count, point, work->scratch);
        double bounds[3] = {INFINITY, INFINITY, INFINITY};
        if (i > 0 && best[-1] < INFINITY) { /* best[-1]: the k1-th of the point before */
            bounds[0] = OWN_LEAF_GUESS * best[-1];
            bounds[1] = leaf_bound(best[-1], work->scratch[i - 1]);
        }
        uint32_t passed = 0;
        for (int tried = 0; tried < 3; tried++) {
            passed = 0;
            for (uint32_t j = 0; j < own->count; j++) {
                work->passing[passed] = j;
                passed += work->scratch[j] <= bounds[tried];
            }
            if (passed >= (uint32_t)k1 || !(bounds[tried] < INFINITY)) {
                break;
            }
        }
        int filled = 0;
        uint32_t candidate = 0;
        for (; candidate < passed && filled < k1; candidate++, filled++) {
            uint32_t j = work->passing[candidate];
            double squared = work->scratch[j];
            int slot = filled;
            while (slot > 0 && best[slot - 1] > squared) {
                best[slot] = best[slot - 1];
                best_at[slot] = best_at[slot - 1];
                slot--;
            }
            best[slot] = squared;
            best_at[slot] = own->start + j;
        }
        double limit = best[k1 - 1];
        uint8_t equal = filled < k1; /* as scan_leaf leaves it: a list not full */
        for (; candidate < passed; candidate++) {
            uint32_t j = work->passing[candidate];
            offer(best, best_at, k1, work->scratch[j], own->start + j, &limit, &equal);
        }
        work->equal[i] = equal;
    }
}

/* The k1 nearest in ``tree`` of each point of one leaf of ``own_tree`` (the same tree for a
   cloud's own neighbours, another cloud's for its nearest points there); the number of its
   points whose order is not unique (two of the k1 + 1 nearest equally far, or fewer than k1
   points in the tree).  Outputs are at the points' rows of ``own_tree``'s array. */
static Py_ssize_t search_leaf(const Tree *own_tree, const Node *own, const Tree *tree, int k1,
                              uint32_t *index_out, double *kth_out, uint8_t *tie_out, Work *work)
{
    for (size_t i = 0; i < (size_t)own->count * k1; i++) {
        work->best[i] = INFINITY;
        work->best_at[i] = 0;
    }
    memset(work->equal, 0, own->count);
    double worst = INFINITY;
    int fresh = 1; /* no leaf scanned yet: every list empty */
    int top = 0;
    work->stack[top++] = 0;
    while (top > 0) {
        const Node *node = &tree->nodes[work->stack[--top]];
        if (box_gap(own, node) > worst) {
            continue;
        }
        if (node->left < 0) {
            if (fresh && node == own && own_tree == tree && k1 > 1) {
                scan_own_leaf(tree, own, k1, work);
            }
            else {
                scan_leaf(own_tree, own, tree, node, k1, work);
            }
            fresh = 0;
            worst = 0.0;
            for (uint32_t i = 0; i < own->count; i++) {
                double kth = work->best[(size_t)i * k1 + k1 - 1];
                worst = kth > worst ? kth : worst;
            }
            continue;
        }
        /* the nearer child is searched first (pushed last) */
        int32_t near = node->left, far = node->right;
        double near_gap = box_gap(own, &tree->nodes[near]);
        double far_gap = box_gap(own, &tree->nodes[far]);
        if (far_gap < near_gap) {
            int32_t swapped = near;
            near = far;
            far = swapped;
            double gap = near_gap;
            near_gap = far_gap;
            far_gap = gap;
        }
        if (far_gap <= worst) {
            work->stack[top++] = far;
        }
        if (near_gap <= worst) {
            work->stack[top++] = near;
        }
    }
    Py_ssize_t ties = 0;
    for (uint32_t i = 0; i < own->count; i++) {
        const double *best = work->best + (size_t)i * k1;
        const uint32_t *best_at = work->best_at + (size_t)i * k1;
        size_t row = own_tree->row[own->start + i];
        uint8_t tie = (uint8_t)(!(best[k1 - 1] < INFINITY)) | work->equal[i];
        for (int slot = 1; slot < k1; slot++) {
            tie |= !(best[slot - 1] < best[slot]);
        }
        for (int slot = 0; slot < k1; slot++) {
            index_out[row * k1 + slot] = tree->row[best_at[slot]];
        }
        kth_out[row] = best[k1 - 1];
        tie_out[row] = tie;
        ties += tie;
    }
    return ties;
}

/* ---- Python ---- */

typedef struct {
    PyObject_HEAD Tree tree;
} TreeObject;

static void tree_dealloc(TreeObject *self)
{
    free_tree(&self->tree);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyTypeObject TreeType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "app.core.localise._knn_kernel.Tree",
    .tp_basicsize = sizeof(TreeObject),
    .tp_dealloc = (destructor)tree_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A k-d tree over an (n, 3) float64 array (build_tree).",
};

static int float64_rows(Py_buffer *view, Py_ssize_t *n)
{
    if (view->ndim != 2 || view->shape[1] != 3 || view->itemsize != 8 ||
        view->format == NULL || strcmp(view->format, "d") != 0 ||
        !PyBuffer_IsContiguous(view, 'C')) {
        PyErr_SetString(PyExc_ValueError, "points must be a C-contiguous (n, 3) float64 array");
        return -1;
    }
    *n = view->shape[0];
    return 0;
}

static int tree_of_points(Tree *tree, const double *points, Py_ssize_t n)
{
    memset(tree, 0, sizeof(Tree));
    tree->n = n;
    for (int d = 0; d < 3; d++) {
        tree->axis[d] = malloc(sizeof(double) * (size_t)n);
    }
    tree->row = malloc(sizeof(uint32_t) * (size_t)n);
    if (!tree->axis[0] || !tree->axis[1] || !tree->axis[2] || !tree->row) {
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        for (int d = 0; d < 3; d++) {
            tree->axis[d][i] = points[3 * i + d];
        }
        tree->row[i] = (uint32_t)i;
    }
    if (build(tree, 0, (uint32_t)n, 1) < 0) {
        return -1;
    }
    tree->leaves = malloc(sizeof(int32_t) * (size_t)tree->n_nodes);
    if (tree->leaves == NULL) {
        return -1;
    }
    collect_leaves(tree, 0);
    return 0;
}

static PyObject *build_tree(PyObject *module, PyObject *args)
{
    PyObject *points;
    Py_buffer view;
    if (!PyArg_ParseTuple(args, "O", &points) ||
        PyObject_GetBuffer(points, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        return NULL;
    }
    Py_ssize_t n;
    if (float64_rows(&view, &n) < 0 || n < 1 || n > (Py_ssize_t)UINT32_MAX) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_ValueError, "points must have 1 .. 2**32 - 1 rows");
        }
        PyBuffer_Release(&view);
        return NULL;
    }
    TreeObject *self = PyObject_New(TreeObject, &TreeType);
    if (self == NULL) {
        PyBuffer_Release(&view);
        return NULL;
    }
    int failed;
    Py_BEGIN_ALLOW_THREADS
    failed = tree_of_points(&self->tree, view.buf, n);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    if (failed) {
        Py_DECREF(self);
        return PyErr_NoMemory();
    }
    return (PyObject *)self;
}

static int writable(Py_buffer *view, Py_ssize_t bytes, const char *name)
{
    if (view->len != bytes || !PyBuffer_IsContiguous(view, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s has the wrong size or layout", name);
        return -1;
    }
    return 0;
}

static void free_work(Work *work)
{
    free(work->stack);
    free(work->best);
    free(work->best_at);
    free(work->equal);
    free(work->scratch);
    free(work->passing);
}

/* Work space for the points of ``own``'s leaves searching ``tree`` for k1 nearest; 0, or -1
   when out of memory (then nothing is left allocated). */
static int new_work(Work *work, const Tree *own, const Tree *tree, int k1)
{
    size_t own_most = own->largest_leaf > LEAF_SIZE ? own->largest_leaf : LEAF_SIZE;
    size_t most = tree->largest_leaf > LEAF_SIZE ? tree->largest_leaf : LEAF_SIZE;
    work->stack = malloc(sizeof(int32_t) * (size_t)(tree->depth + 2));
    work->best = malloc(sizeof(double) * own_most * (size_t)k1);
    work->best_at = malloc(sizeof(uint32_t) * own_most * (size_t)k1);
    work->equal = malloc(own_most);
    work->scratch = malloc(sizeof(double) * most);
    work->passing = malloc(sizeof(uint32_t) * most);
    if (work->stack && work->best && work->best_at && work->equal && work->scratch &&
        work->passing) {
        return 0;
    }
    free_work(work);
    return -1;
}

static PyObject *self_neighbours(PyObject *module, PyObject *args)
{
    TreeObject *self;
    int k1;
    Py_buffer index_out, kth_out, tie_out, cancel;
    Py_ssize_t first = 0, last = -1;
    if (!PyArg_ParseTuple(args, "O!iw*w*w*w*|nn", &TreeType, &self, &k1, &index_out, &kth_out,
                          &tie_out, &cancel, &first, &last)) {
        return NULL;
    }
    const Tree *tree = &self->tree;
    PyObject *result = NULL;
    if (last < 0 || last > tree->n_leaves) {
        last = tree->n_leaves;
    }
    if (first < 0 || first > last) {
        PyErr_SetString(PyExc_ValueError, "leaves out of range");
    }
    else if (k1 < 1 || k1 >= MAX_NEIGHBOURS || k1 > tree->n) {
        PyErr_SetString(PyExc_ValueError, "k + 1 must be in 1 .. min(n, 255)");
    }
    else if (tree->largest_leaf > MAX_LEAF) {
        PyErr_SetString(PyExc_ValueError, "too many equal points for the kernel");
    }
    else if (writable(&index_out, tree->n * k1 * 4, "index_out") == 0 &&
             writable(&kth_out, tree->n * 8, "kth_out") == 0 &&
             writable(&tie_out, tree->n, "tie_out") == 0 && writable(&cancel, 1, "cancel") == 0) {
        Work work;
        if (new_work(&work, tree, tree, k1) == 0) {
            Py_ssize_t ties = 0, leaf = first;
            volatile const uint8_t *cancelled = cancel.buf;
            Py_BEGIN_ALLOW_THREADS
            for (; leaf < last && !*cancelled; leaf++) {
                ties += search_leaf(tree, &tree->nodes[tree->leaves[leaf]], tree, k1,
                                    index_out.buf, kth_out.buf, tie_out.buf, &work);
            }
            Py_END_ALLOW_THREADS
            result = PyLong_FromSsize_t(leaf < last ? -1 : ties);
            free_work(&work);
        }
        else {
            PyErr_NoMemory();
        }
    }
    PyBuffer_Release(&index_out);
    PyBuffer_Release(&kth_out);
    PyBuffer_Release(&tie_out);
    PyBuffer_Release(&cancel);
    return result;
}

static PyObject *nearest_other(PyObject *module, PyObject *args)
{
    TreeObject *own_object, *other_object;
    Py_buffer index_out, squared_out, tie_out;
    Py_ssize_t first = 0, last = -1;
    if (!PyArg_ParseTuple(args, "O!O!w*w*w*|nn", &TreeType, &own_object, &TreeType,
                          &other_object, &index_out, &squared_out, &tie_out, &first, &last)) {
        return NULL;
    }
    const Tree *own = &own_object->tree, *other = &other_object->tree;
    PyObject *result = NULL;
    if (last < 0 || last > own->n_leaves) {
        last = own->n_leaves;
    }
    Work work;
    if (first < 0 || first > last) {
        PyErr_SetString(PyExc_ValueError, "leaves out of range");
    }
    else if (own->largest_leaf > MAX_LEAF || other->largest_leaf > MAX_LEAF) {
        PyErr_SetString(PyExc_ValueError, "too many equal points for the kernel");
    }
    else if (writable(&index_out, own->n * 4, "index_out") == 0 &&
             writable(&squared_out, own->n * 8, "squared_out") == 0 &&
             writable(&tie_out, own->n, "tie_out") == 0) {
        if (new_work(&work, own, other, 1) == 0) {
            Py_ssize_t ties = 0;
            Py_BEGIN_ALLOW_THREADS
            for (Py_ssize_t leaf = first; leaf < last; leaf++) {
                ties += search_leaf(own, &own->nodes[own->leaves[leaf]], other, 1,
                                    index_out.buf, squared_out.buf, tie_out.buf, &work);
            }
            Py_END_ALLOW_THREADS
            result = PyLong_FromSsize_t(ties);
            free_work(&work);
        }
        else {
            PyErr_NoMemory();
        }
    }
    PyBuffer_Release(&index_out);
    PyBuffer_Release(&squared_out);
    PyBuffer_Release(&tie_out);
    return result;
}

static PyObject *leaf_count(PyObject *module, PyObject *args)
{
    TreeObject *self;
    if (!PyArg_ParseTuple(args, "O!", &TreeType, &self)) {
        return NULL;
    }
    return PyLong_FromSsize_t(self->tree.n_leaves);
}

static PyObject *tree_order(PyObject *module, PyObject *args)
{
    TreeObject *self;
    Py_buffer order_out;
    if (!PyArg_ParseTuple(args, "O!w*", &TreeType, &self, &order_out)) {
        return NULL;
    }
    const Tree *tree = &self->tree;
    int failed = writable(&order_out, tree->n * (Py_ssize_t)sizeof(int64_t), "order_out");
    if (failed == 0) {
        int64_t *order = order_out.buf;
        for (Py_ssize_t i = 0; i < tree->n; i++) {
            order[i] = tree->row[i];
        }
    }
    PyBuffer_Release(&order_out);
    if (failed) {
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"leaf_count", leaf_count, METH_VARARGS, "leaf_count(tree) -> int: the tree's leaves."},
    {"tree_order", tree_order, METH_VARARGS,
     "tree_order(tree, order_out) -> None\n\n"
     "The rows of the points in tree order (leaf after leaf, each leaf's points together)\n"
     "into order_out ((n,) int64): a spatial order of the cloud."},
    {"build_tree", build_tree, METH_VARARGS,
     "build_tree(points) -> Tree: a k-d tree over a C-contiguous (n, 3) float64 array."},
    {"self_neighbours", self_neighbours, METH_VARARGS,
     "self_neighbours(tree, k1, index_out, kth_out, tie_out, cancel, first=0, last=-1) -> int\n\n"
     "The points of leaves first .. last - 1 (last -1: all; leaves are disjoint, so two\n"
     "threads may share the arrays): each one's k1 nearest points (itself first), ascending,\n"
     "into index_out ((n, k1)\n"
     "uint32), the k1-th squared distance into kth_out ((n,) float64) and 1 into tie_out\n"
     "((n,) uint8) where two of the k1 + 1 nearest are equally far (their order is then\n"
     "not unique).  Stops when cancel[0] becomes non-zero.  Returns the number of tied\n"
     "points, or -1 when cancelled.  Runs without the GIL."},
    {"nearest_other", nearest_other, METH_VARARGS,
     "nearest_other(own, other, index_out, squared_out, tie_out, first=0, last=-1) -> int\n\n"
     "Each point of own's leaves first .. last - 1 (last -1: all): its nearest point in the\n"
     "tree other, into index_out ((n,) uint32, rows of other's array), the squared distance\n"
     "into squared_out ((n,) float64) and 1 into tie_out ((n,) uint8) where two of other's\n"
     "points are equally near (which one pykdtree gives is then its walk's); n is own's\n"
     "size, outputs at own's rows.  Returns the number of tied points.  Without the GIL."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "app.core.localise._knn_kernel",
    "Every point's k nearest neighbours in its own cloud (see _knn_kernel.c).", -1, methods,
};

PyMODINIT_FUNC PyInit__knn_kernel(void)
{
    if (PyType_Ready(&TreeType) < 0) {
        return NULL;
    }
    return PyModule_Create(&module);
}
