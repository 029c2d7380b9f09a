/* The Python-facing choice of a kernel's instruction-set variant, shared by silu.c and moments.c:
 * isa(), supported_isas() and use_isa(name), for tests and measurements (the best variant this
 * CPU runs is the default).
 *
 * The including file defines, before the #include: an array VARIANTS whose elements have the
 * fields `const char *name` and `int supported` (set at import by its own detection), N_VARIANTS,
 * and `static int CURRENT`, the index in use (-1 where the CPU runs none). */
#ifndef SOFTAE_ISA_VARIANTS_H
#define SOFTAE_ISA_VARIANTS_H

#include <Python.h>
#include <string.h>

static PyObject *isa(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    if (CURRENT < 0) Py_RETURN_NONE;
    return PyUnicode_FromString(VARIANTS[CURRENT].name);
}

static PyObject *supported_isas(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    PyObject *out = PyList_New(0);
    for (int i = 0; out != NULL && i < N_VARIANTS; i++) {
        if (!VARIANTS[i].supported) continue;
        PyObject *name = PyUnicode_FromString(VARIANTS[i].name);
        if (name == NULL || PyList_Append(out, name) < 0) Py_CLEAR(out);
        Py_XDECREF(name);
    }
    return out;
}

static PyObject *use_isa(PyObject *self, PyObject *args) {
    const char *name;
    (void)self;
    if (!PyArg_ParseTuple(args, "s", &name)) return NULL;
    for (int i = 0; i < N_VARIANTS; i++) {
        if (strcmp(VARIANTS[i].name, name) == 0 && VARIANTS[i].supported) {
            CURRENT = i;
            Py_RETURN_NONE;
        }
    }
    PyErr_Format(PyExc_ValueError, "use_isa: %s is not an instruction set this CPU runs the kernel on", name);
    return NULL;
}

#define SOFTAE_ISA_METHODS                                                                                   \
    {"isa", isa, METH_NOARGS, "the instruction set the kernel runs on (None: none this CPU runs)"},          \
        {"supported_isas", supported_isas, METH_NOARGS, "the instruction sets this CPU can run the kernel on"}, \
        {"use_isa", use_isa, METH_VARARGS, "use_isa(name): run on this instruction set (one of supported_isas())"}

#endif
