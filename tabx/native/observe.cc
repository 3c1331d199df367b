// The observation's assembly on the CPU, as an XLA FFI kernel (tabx/observe_kernel.py).
//
// XLA:CPU builds the viewer-relative cyclic order of the other units (i+1 .. N-1, 0 .. i-1)
// from 2N slices and one concatenate per step, kernels that copy a few floats per env each;
// at 5v5 they were over half of a random-action step. This loop writes each observation row
// once. It computes nothing XLA's version does not: every value is a copy, a 0/1 flag, or
// (p_j - p_i) * (1 / half), the same float operations in the same order (compiled without
// fast math or FMA contraction), so both give the same bits (tests/test_observe_kernel.py).
//
// Operands, all with the same leading batch dimensions (flattened to `envs` here):
//   own (N, 14) f32        every unit's own features, already masked (tabx.observe)
//   position (N, 2) f32    positions
//   inv_half (2,) f32      1 / (arena size / 2)
//   team (N,) s32          team of each slot
//   seen (N, N) pred       viewer i sees unit j (visibility and both slots active)
//   attackable (N, N) pred viewer i can attack unit j now
//   zones (N, ZF) f32      each viewer's zone features, already flattened and masked
// Result (N, 14 + 16 (N - 1) + ZF) f32: [own i | other blocks in cyclic order | zones i].
#include <cstdint>
#include <cstring>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int64_t kOwn = 14;
constexpr int64_t kOther = 16;

ffi::Error AssembleObservation(ffi::Buffer<ffi::F32> own, ffi::Buffer<ffi::F32> position,
                               ffi::Buffer<ffi::F32> inv_half, ffi::Buffer<ffi::S32> team,
                               ffi::Buffer<ffi::PRED> seen, ffi::Buffer<ffi::PRED> attackable,
                               ffi::Buffer<ffi::F32> zones, ffi::ResultBuffer<ffi::F32> out) {
  const auto own_dims = own.dimensions();
  const auto zone_dims = zones.dimensions();
  if (own_dims.size() < 2 || own_dims.back() != kOwn || zone_dims.size() < 2) {
    return ffi::Error::InvalidArgument("tabx_assemble_observation: own must be (..., N, 14)");
  }
  const int64_t n = own_dims[own_dims.size() - 2];
  const int64_t zf = zone_dims.back();
  const int64_t envs = n > 0 ? own.element_count() / (n * kOwn) : 0;
  const int64_t row = kOwn + kOther * (n - 1) + zf;
  if (position.element_count() != envs * n * 2 || inv_half.element_count() != envs * 2 ||
      team.element_count() != envs * n || seen.element_count() != envs * n * n ||
      attackable.element_count() != envs * n * n || zones.element_count() != envs * n * zf ||
      out->element_count() != envs * n * row) {
    return ffi::Error::InvalidArgument("tabx_assemble_observation: inconsistent shapes");
  }
  const float* own_all = own.typed_data();
  const float* pos_all = position.typed_data();
  const float* inv_all = inv_half.typed_data();
  const int32_t* team_all = team.typed_data();
  const bool* seen_all = seen.typed_data();
  const bool* att_all = attackable.typed_data();
  const float* zone_all = zones.typed_data();
  float* out_all = out->typed_data();

  for (int64_t e = 0; e < envs; ++e) {
    const float* o = own_all + e * n * kOwn;
    const float* p = pos_all + e * n * 2;
    const float inv_x = inv_all[e * 2];
    const float inv_y = inv_all[e * 2 + 1];
    const int32_t* t = team_all + e * n;
    const bool* s = seen_all + e * n * n;
    const bool* a = att_all + e * n * n;
    const float* z = zone_all + e * n * zf;
    for (int64_t i = 0; i < n; ++i) {
      float* r = out_all + (e * n + i) * row;
      std::memcpy(r, o + i * kOwn, kOwn * sizeof(float));
      r += kOwn;
      for (int64_t k = 0; k < n - 1; ++k, r += kOther) {
        const int64_t j = i + 1 + k < n ? i + 1 + k : i + 1 + k - n;
        if (!s[i * n + j]) {
          std::memset(r, 0, kOther * sizeof(float));
          continue;
        }
        const float* oj = o + j * kOwn;
        r[0] = oj[0];  // health, health ratio
        r[1] = oj[1];
        r[2] = (p[j * 2] - p[i * 2]) * inv_x;  // relative position
        r[3] = (p[j * 2 + 1] - p[i * 2 + 1]) * inv_y;
        std::memcpy(r + 4, oj + 4, 9 * sizeof(float));  // heading .. alive
        r[13] = t[i] == t[j] ? 1.0f : 0.0f;  // is ally
        r[14] = a[i * n + j] ? 1.0f : 0.0f;  // attackable by the viewer
        r[15] = oj[13];  // speed
      }
      std::memcpy(r, z + i * zf, zf * sizeof(float));
    }
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(TabxAssembleObservation, AssembleObservation,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());
