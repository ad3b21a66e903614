/* The exported function of unet_layout.c (the U-Net input's channels_last copy): the ctypes bindings of
   deliffas/models/unet_cpu.py are read from this prototype (deliffas/native.py, declare). */
#ifndef DELIFFAS_UNET_LAYOUT_H
#define DELIFFAS_UNET_LAYOUT_H
#include <stdint.h>

void deliffas_planar_to_interleaved_f32(const float *src, float *dst, int64_t batch, int64_t channels,
                                        int64_t pixels);

#endif
