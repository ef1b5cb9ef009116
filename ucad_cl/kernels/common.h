/* Shared constants and helpers for every ucad-cl kernel.
 *
 * Numerics are explicit: no floating-point contraction (a*b+c is never fused behind our back),
 * so the same source gives the same bits on every conforming device. Where exactness matters we
 * use fixed point (see raster_common.h: 8 sub-pixel bits, 64-bit edge functions).
 */
#ifndef UCAD_COMMON_H
#define UCAD_COMMON_H
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable

/* Constants shared with the host come from ucad_cl/abi.py as -D options (Runtime.program adds
 * them to every build); a build without them stops here rather than use a stale copy. */
#if !defined(UCAD_BG_TRI) || !defined(UCAD_BG_MAT) || !defined(BIG_PIXELS) || !defined(MAX_BINS) \
    || !defined(KMAX) || !defined(SRGB_BUCKETS) || !defined(MAX_PARTS)
#error "built without the ABI defines of ucad_cl/abi.py (build through ucad_cl.runtime.Runtime)"
#endif

/* The 16 values p[ix.s0] .. p[ix.sf] as a T vector, for kernels written in explicit 16-lane
 * vectors (raster_serial.cl, shade.cl). The offsets are cast to signed 32 bits, which lets
 * LLVM use 16-wide dword gathers (every index used is below 2^31). */
#define GATHER16(T, p, ix) (T)(                                                                 \
    (p)[(int)(ix).s0], (p)[(int)(ix).s1], (p)[(int)(ix).s2], (p)[(int)(ix).s3],                 \
    (p)[(int)(ix).s4], (p)[(int)(ix).s5], (p)[(int)(ix).s6], (p)[(int)(ix).s7],                 \
    (p)[(int)(ix).s8], (p)[(int)(ix).s9], (p)[(int)(ix).sa], (p)[(int)(ix).sb],                 \
    (p)[(int)(ix).sc], (p)[(int)(ix).sd], (p)[(int)(ix).se], (p)[(int)(ix).sf])

#endif
