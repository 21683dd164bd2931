// Front-to-back alpha compositing of depth-sorted 2D Gaussians per 16x16 tile (3DGS, Kerbl et al.
// 2023, section 6), forward and backward, on the CPU with OpenMP over tiles (dynamic schedule).
//
// Semantics (identical to mogs_node/mapper/composite.py:composite_torch and to the per-pixel
// reference): for each pixel, in list order, power = -0.5 (a dx^2 + c dy^2) - b dx dy with
// d = mean - pixel; skip when opacity * exp(power) < alpha_min; alpha = min(alpha_max, ...);
// stop (without this Gaussian) when T * (1 - alpha) < t_min; out += f * alpha * T.
// The backward pass walks each pixel's list back to front (3DGS backward), recovering T by division.
// The forward also returns each list entry's summed blending weight sum_p alpha T over the tile's
// pixels (entry_w, one slot per entry, so no float atomics); the caller sums them per Gaussian.
// The backward writes each list entry's gradient (the sums over its tile's pixels) into its own
// slot, then one serial pass adds the slots into each Gaussian's gradient in list order (tile by
// tile, the order a single thread visits them): no float atomics, and bitwise the same gradients
// for ANY thread count and schedule, the same as one thread's. So the thread count is a speed
// setting only: two threads give the map of one (and the forward is thread-count free too).
#include <torch/extension.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>
#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int kMaxC = 8;

template <typename scalar_t>
struct Packed {
  scalar_t mx, my, a, b, c, o, thr;  // thr = log(alpha_min / o): skip when power < thr
  scalar_t ey;                        // half height of the support box (pixels)
  int64_t id;
};

template <typename scalar_t>
void pack_tile(const int64_t* ids, int64_t n, const scalar_t* means2d, const scalar_t* conics,
               const scalar_t* opac, const scalar_t* ext, double alpha_min,
               std::vector<Packed<scalar_t>>& buf) {
  buf.resize(n);
  for (int64_t k = 0; k < n; ++k) {
    const int64_t g = ids[k];
    Packed<scalar_t>& p = buf[k];
    p.mx = means2d[2 * g];
    p.my = means2d[2 * g + 1];
    p.a = conics[3 * g];
    p.b = conics[3 * g + 1];
    p.c = conics[3 * g + 2];
    p.o = opac[g];
    p.thr = p.o > 0 ? static_cast<scalar_t>(std::log(alpha_min / static_cast<double>(p.o)))
                    : static_cast<scalar_t>(INFINITY);
    p.ey = ext[2 * g + 1];
    p.id = g;
  }
}

// What both passes read: the depth-sorted tile lists, the screen-space Gaussians (means2d [N, 2],
// conics [N, 3], opacity [N], support half-widths ext [N, 2]), their features [N, C], the
// background [C] and the alpha clamp.
template <typename scalar_t>
struct TileInputs {
  int64_t C, n_tiles;
  const int64_t* offs;
  const int64_t* ids;
  const scalar_t *m2, *co, *op, *fe, *bgp, *ex;
  scalar_t amax, amin;

  TileInputs(const torch::Tensor& tile_offsets, const torch::Tensor& gauss_ids,
             const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
             const torch::Tensor& feats, const torch::Tensor& bg, const torch::Tensor& ext,
             double alpha_min, double alpha_max)
      : C(feats.size(1)),
        n_tiles(tile_offsets.size(0) - 1),
        offs(tile_offsets.data_ptr<int64_t>()),
        ids(gauss_ids.data_ptr<int64_t>()),
        m2(means2d.data_ptr<scalar_t>()),
        co(conics.data_ptr<scalar_t>()),
        op(opac.data_ptr<scalar_t>()),
        fe(feats.data_ptr<scalar_t>()),
        bgp(bg.data_ptr<scalar_t>()),
        ex(ext.data_ptr<scalar_t>()),
        amax(static_cast<scalar_t>(alpha_max)),
        amin(static_cast<scalar_t>(alpha_min)) {}

  // The first n entries of tile t's list, packed (pack_tile).
  void pack(int64_t t, int64_t n, double alpha_min, std::vector<Packed<scalar_t>>& buf) const {
    pack_tile<scalar_t>(ids + offs[t], n, m2, co, op, ex, alpha_min, buf);
  }
};

// Pixel rows [y0, y1] of the tile that the Gaussian's support box reaches (empty if y0 > y1).
template <typename scalar_t>
inline void row_range(const Packed<scalar_t>& p, int64_t py0, int64_t py1, int64_t& y0,
                      int64_t& y1) {
  const double lo = std::max(static_cast<double>(py0), std::ceil(double(p.my) - double(p.ey)));
  const double hi = std::min(static_cast<double>(py1 - 1), std::floor(double(p.my) + double(p.ey)));
  if (!(lo <= hi)) {
    y0 = 1;
    y1 = 0;
    return;
  }
  y0 = static_cast<int64_t>(lo);
  y1 = static_cast<int64_t>(hi);
}

// Pixel columns [x0, x1] of row y where power >= thr can hold: a superset of the exact ellipse
// chord a dx^2 + 2 b dy dx + c dy^2 + 2 thr <= 0 (dx = mx - x), widened by a small margin, so
// the in-loop test remains the only decision (results identical to a full scan).
template <typename scalar_t>
inline bool col_range(const Packed<scalar_t>& p, int64_t y, int64_t px0, int64_t px1,
                      int64_t& x0, int64_t& x1) {
  const double a = p.a, b = p.b, c = p.c, dy = double(p.my) - double(y);
  const double q = c * dy * dy + 2.0 * double(p.thr);
  const double disc = b * b * dy * dy - a * q;
  const double scale = b * b * dy * dy + std::abs(a * q);
  if (!(disc >= -1e-5 * scale) || !(a > 0)) return false;
  const double half = std::sqrt(std::max(disc, 0.0)) / a;
  const double centre = double(p.mx) + b * dy / a;  // x at the chord centre
  const double m = 0.05 + 1e-4 * half;
  const double lo = std::max(static_cast<double>(px0), std::ceil(centre - half - m));
  const double hi = std::min(static_cast<double>(px1 - 1), std::floor(centre + half + m));
  if (!(lo <= hi)) return false;
  x0 = static_cast<int64_t>(lo);
  x1 = static_cast<int64_t>(hi);
  return true;
}

// The forward's contributions, for the backward: per tile, in the order the forward visits them
// (entries front to back, each entry's pixels row by row), exp(power) and the pixel (index in the
// tile); per list entry, how many contributions it made. The backward replays exactly these
// (the set of pixel-entry pairs it must visit is the forward's contributions: the entries before
// a pixel's last contributor that pass the alpha tests), so it needs no chord geometry, no power
// tests and no exp, and its arithmetic is the same as recomputing them (bitwise the same G).
template <typename scalar_t>
struct RecordBuffer {  // one thread's contributions, tile after tile: (tile, start, length)
  std::vector<scalar_t> G;
  std::vector<int16_t> px;
  std::vector<std::array<int64_t, 3>> segments;
};

// Each thread's buffer lives as long as the thread (OpenMP keeps its pool): its capacity stays,
// so a forward neither reallocates nor faults fresh pages for the record once warmed up.
template <typename scalar_t>
RecordBuffer<scalar_t>& thread_record_buffer() {
  static thread_local RecordBuffer<scalar_t> buf;
  return buf;
}

template <typename scalar_t>
struct Record {
  std::vector<RecordBuffer<scalar_t>*> buffers;  // by thread number
  int32_t* entry_n;                              // [M], zero where the forward stopped before it
};

inline int thread_num() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

template <typename scalar_t>
void forward_kernel(const torch::Tensor& tile_offsets, const torch::Tensor& gauss_ids,
                    const torch::Tensor& means2d, const torch::Tensor& conics,
                    const torch::Tensor& opac, const torch::Tensor& feats, const torch::Tensor& bg,
                    const torch::Tensor& ext, int64_t W, int64_t H, int64_t tile, int64_t tiles_x,
                    double alpha_min, double alpha_max, double t_min, int nthreads,
                    torch::Tensor& out, torch::Tensor& final_T, torch::Tensor& n_contrib,
                    torch::Tensor& counts, torch::Tensor& entry_w, Record<scalar_t>* rec) {
  const TileInputs<scalar_t> in(tile_offsets, gauss_ids, means2d, conics, opac, feats, bg, ext,
                                alpha_min, alpha_max);
  const int64_t C = in.C;
  const int64_t* offs = in.offs;
  const scalar_t* fe = in.fe;
  scalar_t* outp = out.data_ptr<scalar_t>();
  scalar_t* Tp = final_T.data_ptr<scalar_t>();
  int32_t* ncp = n_contrib.data_ptr<int32_t>();
  int32_t* cnt = counts.data_ptr<int32_t>();
  scalar_t* ewp = entry_w.data_ptr<scalar_t>();
  const scalar_t amax = in.amax, amin = in.amin;
  const scalar_t tmin = static_cast<scalar_t>(t_min);
  const int64_t P = tile * tile;

#pragma omp parallel num_threads(nthreads)
  {
    std::vector<Packed<scalar_t>> buf;
    std::vector<scalar_t> T(P), acc(P * C);
    std::vector<int32_t> last(P);
    std::vector<char> done(P);
    RecordBuffer<scalar_t>* rb = nullptr;
    if (rec) {
      rb = &thread_record_buffer<scalar_t>();
      rb->G.clear();
      rb->px.clear();
      rb->segments.clear();
      rec->buffers[thread_num()] = rb;
    }
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < in.n_tiles; ++t) {
      const int64_t n = offs[t + 1] - offs[t];
      in.pack(t, n, alpha_min, buf);
      const int64_t px0 = (t % tiles_x) * tile, py0 = (t / tiles_x) * tile;
      const int64_t px1 = std::min(px0 + tile, W), py1 = std::min(py0 + tile, H);
      const int64_t n_pix = (px1 - px0) * (py1 - py0);
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(last.begin(), last.end(), 0);
      std::fill(done.begin(), done.end(), 0);
      const int64_t rec_start = rb ? static_cast<int64_t>(rb->G.size()) : 0;
      int32_t* rec_n = rec ? rec->entry_n + offs[t] : nullptr;
      int64_t n_done = 0;
      for (int64_t k = 0; k < n && n_done < n_pix; ++k) {
        const Packed<scalar_t>& p = buf[k];
        const scalar_t* f = fe + p.id * C;
        int64_t y0, y1, x0, x1;
        row_range(p, py0, py1, y0, y1);
        int32_t used = 0;
        scalar_t w_sum = 0;
        for (int64_t y = y0; y <= y1; ++y) {
          if (!col_range(p, y, px0, px1, x0, x1)) continue;
          const scalar_t dy = p.my - static_cast<scalar_t>(y);
          for (int64_t x = x0; x <= x1; ++x) {
            const int64_t i = (y - py0) * tile + (x - px0);
            if (done[i]) continue;
            const scalar_t dx = p.mx - static_cast<scalar_t>(x);
            const scalar_t power = -static_cast<scalar_t>(0.5) * (p.a * dx * dx + p.c * dy * dy) -
                                   p.b * dx * dy;
            if (power > 0 || power < p.thr) continue;
            const scalar_t G = std::exp(power);
            const scalar_t alpha = std::min(amax, p.o * G);
            if (alpha < amin) continue;
            const scalar_t test_T = T[i] * (1 - alpha);
            if (test_T < tmin) {
              done[i] = 1;
              ++n_done;
              continue;
            }
            const scalar_t w = alpha * T[i];
            scalar_t* ai = acc.data() + i * C;
            for (int64_t ch = 0; ch < C; ++ch) ai[ch] += f[ch] * w;
            T[i] = test_T;
            last[i] = static_cast<int32_t>(k + 1);
            ++used;
            w_sum += w;
            if (rb) {  // what the backward needs of this contribution, in visiting order
              rb->G.push_back(G);
              rb->px.push_back(static_cast<int16_t>(i));
            }
          }
        }
        if (rb) rec_n[k] = used;
        if (used) __atomic_fetch_add(cnt + p.id, used, __ATOMIC_RELAXED);
        ewp[offs[t] + k] = w_sum;  // one slot per list entry: no float atomics, deterministic
      }
      for (int64_t y = py0; y < py1; ++y) {
        for (int64_t x = px0; x < px1; ++x) {
          const int64_t i = (y - py0) * tile + (x - px0);
          const int64_t pix = y * W + x;
          for (int64_t ch = 0; ch < C; ++ch) outp[pix * C + ch] = acc[i * C + ch] + T[i] * in.bgp[ch];
          Tp[pix] = T[i];
          ncp[pix] = last[i];
        }
      }
      if (rb) rb->segments.push_back({t, rec_start, static_cast<int64_t>(rb->G.size()) - rec_start});
    }
  }
}

template <typename scalar_t>
void backward_kernel(const torch::Tensor& tile_offsets, const torch::Tensor& gauss_ids,
                     const torch::Tensor& means2d, const torch::Tensor& conics,
                     const torch::Tensor& opac, const torch::Tensor& feats, const torch::Tensor& bg,
                     const torch::Tensor& ext, const torch::Tensor& final_T,
                     const torch::Tensor& rec_off, const torch::Tensor& rec_G,
                     const torch::Tensor& rec_px, const torch::Tensor& entry_n,
                     const torch::Tensor& grad_out, int64_t W, int64_t H, int64_t tile,
                     int64_t tiles_x, double alpha_min, double alpha_max, int nthreads,
                     torch::Tensor& grad) {
  // grad: [N, 6 + C] zeros: d means2d (2), d conic (3), d opacity (1), d feats (C)
  const TileInputs<scalar_t> in(tile_offsets, gauss_ids, means2d, conics, opac, feats, bg, ext,
                                alpha_min, alpha_max);
  const int64_t C = in.C;
  const int64_t S = 6 + C;
  const scalar_t* fe = in.fe;
  const scalar_t* bgp = in.bgp;
  const scalar_t* Tp = final_T.data_ptr<scalar_t>();
  const int64_t* roff = rec_off.data_ptr<int64_t>();
  const scalar_t* rG = rec_G.data_ptr<scalar_t>();
  const int16_t* rpx = rec_px.data_ptr<int16_t>();
  const int32_t* en = entry_n.data_ptr<int32_t>();
  const scalar_t* go = grad_out.data_ptr<scalar_t>();
  const int64_t M = gauss_ids.size(0);
  // per list entry: its gradient sums (written only where `used`), reduced serially below
  std::vector<scalar_t> slots(static_cast<size_t>(M) * S);
  std::vector<char> used(M, 0);
  const scalar_t amax = in.amax;
  const int64_t P = tile * tile;

#pragma omp parallel num_threads(nthreads)
  {
    std::vector<scalar_t> T(P), Tfin(P), accum(P * C), last_f(P * C), last_alpha(P), dout(P * C),
        bg_dot(P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < in.n_tiles; ++t) {
      if (roff[t + 1] == roff[t]) continue;  // nothing drawn in this tile
      const int64_t px0 = (t % tiles_x) * tile, py0 = (t / tiles_x) * tile;
      const int64_t px1 = std::min(px0 + tile, W), py1 = std::min(py0 + tile, H);
      for (int64_t y = py0; y < py1; ++y) {
        for (int64_t x = px0; x < px1; ++x) {
          const int64_t i = (y - py0) * tile + (x - px0);
          const int64_t pix = y * W + x;
          T[i] = Tfin[i] = Tp[pix];
          scalar_t bd = 0;
          for (int64_t ch = 0; ch < C; ++ch) {
            dout[i * C + ch] = go[pix * C + ch];
            bd += bgp[ch] * go[pix * C + ch];
            accum[i * C + ch] = 0;
            last_f[i * C + ch] = 0;
          }
          bg_dot[i] = bd;
          last_alpha[i] = 0;
        }
      }
      // entries back to front; each entry's contributions in the forward's order
      int64_t r_end = roff[t + 1];
      for (int64_t k = in.offs[t + 1] - in.offs[t] - 1; k >= 0; --k) {
        const int32_t n_rec = en[in.offs[t] + k];
        if (n_rec == 0) continue;
        const int64_t r0 = r_end - n_rec;
        r_end = r0;
        const int64_t id = in.ids[in.offs[t] + k];
        const scalar_t mx = in.m2[2 * id], my = in.m2[2 * id + 1];
        const scalar_t a = in.co[3 * id], b = in.co[3 * id + 1], c = in.co[3 * id + 2];
        const scalar_t o = in.op[id];
        const scalar_t* f = fe + id * C;
        scalar_t gl[6 + kMaxC] = {0};
        for (int64_t r = r0; r < r0 + n_rec; ++r) {
          const int64_t i = rpx[r];
          const scalar_t dx = mx - static_cast<scalar_t>(px0 + i % tile);
          const scalar_t dy = my - static_cast<scalar_t>(py0 + i / tile);
          const scalar_t G = rG[r];
          const scalar_t raw = o * G;
          const scalar_t alpha = std::min(amax, raw);
          T[i] = T[i] / (1 - alpha);
          const scalar_t w = alpha * T[i];
          const scalar_t la = last_alpha[i];
          scalar_t* acc_i = accum.data() + i * C;
          scalar_t* lf_i = last_f.data() + i * C;
          const scalar_t* d_i = dout.data() + i * C;
          scalar_t dL_dalpha = 0;
          for (int64_t ch = 0; ch < C; ++ch) {
            acc_i[ch] = la * lf_i[ch] + (1 - la) * acc_i[ch];
            lf_i[ch] = f[ch];
            dL_dalpha += (f[ch] - acc_i[ch]) * d_i[ch];
            gl[6 + ch] += w * d_i[ch];
          }
          dL_dalpha *= T[i];
          dL_dalpha -= Tfin[i] / (1 - alpha) * bg_dot[i];
          last_alpha[i] = alpha;
          if (raw > amax) continue;  // clamped: alpha does not depend on the parameters
          const scalar_t dL_dpower = alpha * dL_dalpha;
          gl[0] += -dL_dpower * (a * dx + b * dy);
          gl[1] += -dL_dpower * (b * dx + c * dy);
          gl[2] += -static_cast<scalar_t>(0.5) * dx * dx * dL_dpower;
          gl[3] += -dx * dy * dL_dpower;
          gl[4] += -static_cast<scalar_t>(0.5) * dy * dy * dL_dpower;
          gl[5] += G * dL_dalpha;
        }
        const int64_t e = in.offs[t] + k;
        std::copy(gl, gl + S, slots.data() + e * S);
        used[e] = 1;
      }
    }
  }
  // each Gaussian's entries in list order (tiles ascending): the order one thread adds them in
  scalar_t* g = grad.data_ptr<scalar_t>();
  const int64_t* ids = in.ids;
  for (int64_t e = 0; e < M; ++e) {
    if (!used[e]) continue;
    scalar_t* gi = g + ids[e] * S;
    const scalar_t* se = slots.data() + e * S;
    for (int64_t j = 0; j < S; ++j) gi[j] += se[j];
  }
}

// The threads' records as flat tensors in tile order: rec_off [n_tiles + 1] (filled here),
// rec_G, rec_px [R].
template <typename scalar_t>
void pack_record(const Record<scalar_t>& rec, int64_t n_tiles, torch::Tensor& rec_off,
                 torch::Tensor& rec_G, torch::Tensor& rec_px) {
  int64_t* ro = rec_off.data_ptr<int64_t>();
  std::vector<int64_t> len(n_tiles, 0);
  for (const RecordBuffer<scalar_t>* b : rec.buffers) {
    if (b == nullptr) continue;
    for (const auto& sg : b->segments) len[sg[0]] = sg[2];
  }
  int64_t total = 0;
  for (int64_t t = 0; t < n_tiles; ++t) {
    ro[t] = total;
    total += len[t];
  }
  ro[n_tiles] = total;
  rec_G = torch::empty({total}, rec_off.options().dtype(c10::CppTypeToScalarType<scalar_t>::value));
  rec_px = torch::empty({total}, rec_off.options().dtype(torch::kInt16));
  scalar_t* gp = rec_G.data_ptr<scalar_t>();
  int16_t* pp = rec_px.data_ptr<int16_t>();
  for (const RecordBuffer<scalar_t>* b : rec.buffers) {
    if (b == nullptr) continue;
    for (const auto& sg : b->segments) {
      std::copy_n(b->G.data() + sg[1], sg[2], gp + ro[sg[0]]);
      std::copy_n(b->px.data() + sg[1], sg[2], pp + ro[sg[0]]);
    }
  }
}

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics,
                  const torch::Tensor& opac, const torch::Tensor& feats, const torch::Tensor& bg) {
  TORCH_CHECK(means2d.is_contiguous() && conics.is_contiguous() && opac.is_contiguous() &&
                  feats.is_contiguous() && bg.is_contiguous(),
              "composite_cpu: inputs must be contiguous");
  TORCH_CHECK(feats.size(1) <= kMaxC, "composite_cpu: at most 8 feature channels");
}

}  // namespace

std::vector<torch::Tensor> composite_forward(torch::Tensor tile_offsets, torch::Tensor gauss_ids,
                                             torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opac, torch::Tensor feats,
                                             torch::Tensor bg, torch::Tensor ext, int64_t W,
                                             int64_t H, int64_t tile,
                                             int64_t tiles_x, double alpha_min, double alpha_max,
                                             double t_min, int64_t nthreads, bool record) {
  check_inputs(means2d, conics, opac, feats, bg);
  TORCH_CHECK(ext.is_contiguous() && ext.scalar_type() == feats.scalar_type(),
              "composite_forward: ext must be contiguous and of the feature dtype");
  TORCH_CHECK(tile > 0 && tile * tile <= 32768, "composite_forward: tile must be 1..181 pixels");
  const int64_t C = feats.size(1);
  auto out = torch::empty({H, W, C}, feats.options());
  auto final_T = torch::empty({H, W}, feats.options());
  auto n_contrib = torch::empty({H, W}, feats.options().dtype(torch::kInt32));
  auto counts = torch::zeros({means2d.size(0)}, feats.options().dtype(torch::kInt32));
  auto entry_w = torch::zeros({gauss_ids.size(0)}, feats.options());
  const int64_t n_tiles = tile_offsets.size(0) - 1;
  // the record for the backward (empty when no backward follows): rec_off [n_tiles + 1] into
  // rec_G / rec_px [R], entry_n [M] (see Record)
  auto rec_off = torch::zeros({record ? n_tiles + 1 : 0}, feats.options().dtype(torch::kInt64));
  auto entry_n = torch::zeros({record ? gauss_ids.size(0) : 0}, feats.options().dtype(torch::kInt32));
  torch::Tensor rec_G, rec_px;
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "composite_forward", [&] {
    Record<scalar_t> rec;
    if (record) {
      rec.buffers.assign(std::max<int64_t>(nthreads, 1), nullptr);
      rec.entry_n = entry_n.data_ptr<int32_t>();
    }
    forward_kernel<scalar_t>(tile_offsets, gauss_ids, means2d, conics, opac, feats, bg, ext, W, H, tile,
                             tiles_x, alpha_min, alpha_max, t_min, static_cast<int>(nthreads), out,
                             final_T, n_contrib, counts, entry_w, record ? &rec : nullptr);
    if (record) {
      pack_record<scalar_t>(rec, n_tiles, rec_off, rec_G, rec_px);
    } else {
      rec_G = torch::empty({0}, feats.options());
      rec_px = torch::empty({0}, feats.options().dtype(torch::kInt16));
    }
  });
  return {out, final_T, n_contrib, counts, entry_w, rec_off, rec_G, rec_px, entry_n};
}

torch::Tensor composite_backward(torch::Tensor tile_offsets, torch::Tensor gauss_ids,
                                 torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                 torch::Tensor feats, torch::Tensor bg, torch::Tensor ext,
                                 torch::Tensor final_T, torch::Tensor rec_off,
                                 torch::Tensor rec_G, torch::Tensor rec_px, torch::Tensor entry_n,
                                 torch::Tensor grad_out, int64_t W, int64_t H, int64_t tile,
                                 int64_t tiles_x, double alpha_min, double alpha_max,
                                 int64_t nthreads) {
  check_inputs(means2d, conics, opac, feats, bg);
  TORCH_CHECK(grad_out.is_contiguous(), "composite_backward: grad_out must be contiguous");
  TORCH_CHECK(rec_off.size(0) == tile_offsets.size(0) && entry_n.size(0) == gauss_ids.size(0),
              "composite_backward: needs the forward's record (forward with record=true)");
  const int64_t C = feats.size(1);
  auto grad = torch::zeros({means2d.size(0), 6 + C}, feats.options());
  AT_DISPATCH_FLOATING_TYPES(feats.scalar_type(), "composite_backward", [&] {
    backward_kernel<scalar_t>(tile_offsets, gauss_ids, means2d, conics, opac, feats, bg, ext, final_T,
                              rec_off, rec_G, rec_px, entry_n, grad_out, W, H, tile, tiles_x,
                              alpha_min, alpha_max, static_cast<int>(nthreads), grad);
  });
  return grad;
}

// Tile binning (mogs_node/mapper/projection.py:bin_tiles, the same result exactly): the valid
// Gaussians stably sorted by their float32 depth key, each appended to every tile its support box
// [ceil(u - ex), floor(u + ex)] x [ceil(v - ey), floor(v + ey)] (clamped to the image) overlaps, in
// that depth order: a counting sort by tile instead of torch's sort of the expanded list. Returns
// {tile_offsets [n_tiles + 1], gauss_ids [M]}, or {} when a valid Gaussian has a NaN centre or
// extent (the caller's torch path handles those).
std::vector<torch::Tensor> bin_tiles(torch::Tensor depth_key, torch::Tensor valid,
                                     torch::Tensor means2d, torch::Tensor ext, int64_t W, int64_t H,
                                     int64_t tile) {
  TORCH_CHECK(depth_key.scalar_type() == torch::kFloat32 && valid.scalar_type() == torch::kBool,
              "bin_tiles: float32 depth keys and a bool valid mask");
  TORCH_CHECK(depth_key.is_contiguous() && valid.is_contiguous() && tile > 0 && W > 0 && H > 0,
              "bin_tiles: contiguous inputs, positive sizes");
  auto m2 = means2d.to(torch::kFloat64).contiguous();
  auto ex = ext.to(torch::kFloat64).contiguous();
  const int64_t N = depth_key.size(0);
  const float* key = depth_key.data_ptr<float>();
  const bool* ok = valid.data_ptr<bool>();
  const double* uv = m2.data_ptr<double>();
  const double* e = ex.data_ptr<double>();
  std::vector<int64_t> order;
  order.reserve(N);
  for (int64_t i = 0; i < N; ++i) {
    if (!ok[i]) continue;
    if (std::isnan(uv[2 * i]) || std::isnan(uv[2 * i + 1]) || std::isnan(e[2 * i]) ||
        std::isnan(e[2 * i + 1]) || std::isnan(key[i]))
      return {};
    order.push_back(i);
  }
  std::stable_sort(order.begin(), order.end(),
                   [key](int64_t a, int64_t b) { return key[a] < key[b]; });
  const int64_t tiles_x = (W + tile - 1) / tile, tiles_y = (H + tile - 1) / tile;
  const int64_t n_tiles = tiles_x * tiles_y;
  const int64_t n = static_cast<int64_t>(order.size());
  std::vector<int64_t> box(4 * n);  // x0, x1, y0, y1 in tiles (empty when x0 > x1 or y0 > y1)
  auto cell = [tile](double v, double hi) {  // clamp(v, 0, hi).long() // tile, as torch does
    return static_cast<int64_t>(std::min(std::max(v, 0.0), hi)) / tile;
  };
  auto offsets = torch::zeros({n_tiles + 1}, torch::kInt64);
  int64_t* off = offsets.data_ptr<int64_t>();
  for (int64_t j = 0; j < n; ++j) {
    const int64_t g = order[j];
    int64_t* b = box.data() + 4 * j;
    b[0] = cell(std::ceil(uv[2 * g] - e[2 * g]), double(W - 1));
    b[1] = cell(std::floor(uv[2 * g] + e[2 * g]), double(W - 1));
    b[2] = cell(std::ceil(uv[2 * g + 1] - e[2 * g + 1]), double(H - 1));
    b[3] = cell(std::floor(uv[2 * g + 1] + e[2 * g + 1]), double(H - 1));
    for (int64_t ty = b[2]; ty <= b[3]; ++ty)
      for (int64_t tx = b[0]; tx <= b[1]; ++tx) ++off[ty * tiles_x + tx + 1];
  }
  for (int64_t t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  auto ids = torch::empty({off[n_tiles]}, torch::kInt64);
  int64_t* idp = ids.data_ptr<int64_t>();
  std::vector<int64_t> pos(off, off + n_tiles);
  for (int64_t j = 0; j < n; ++j) {
    const int64_t* b = box.data() + 4 * j;
    for (int64_t ty = b[2]; ty <= b[3]; ++ty)
      for (int64_t tx = b[0]; tx <= b[1]; ++tx) idp[pos[ty * tiles_x + tx]++] = order[j];
  }
  return {offsets, ids};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bin_tiles", &bin_tiles, "tile binning (CPU), exactly projection.bin_tiles's result");
  m.def("forward", &composite_forward, "tile compositing forward (CPU)");
  m.def("backward", &composite_backward, "tile compositing backward (CPU)");
}
