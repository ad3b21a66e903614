/* The exported function of encoding.c (positional encodings): the ctypes bindings of deliffas/models/encoding.py
   are read from this prototype (deliffas/native.py, declare). */
#ifndef DELIFFAS_ENCODING_H
#define DELIFFAS_ENCODING_H
#include <stdint.h>

int64_t deliffas_encode_parts_f32(int32_t parts, const float *const *xs, const int32_t *dims, const int32_t *freqs,
                                  const int32_t *include, int64_t n, float *out, int64_t E);

#endif
