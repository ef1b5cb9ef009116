/* Shared constants and helpers for every ucad-cl kernel.
 *
 * Numerics are explicit: no floating-point contraction (a*b+c is never fused behind our back),
 * so the same source gives the same bits on every conforming device. Where exactness matters we
 * use fixed point (see raster.cl: 8 sub-pixel bits, 64-bit edge functions).
 */
#ifndef UCAD_COMMON_H
#define UCAD_COMMON_H
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable

#define UCAD_BG_TRI 0xFFFFFFFFu
#define UCAD_BG_MAT 0u

#endif
