// metegs::parallel_for: the rasteriser's thread pool. Its caller waits only for chunks in flight, never for
// a worker that has not woken up.
//
// at::parallel_for over OpenMP ends every region in a barrier that all of the team's threads must reach. On a
// machine where another process (a browser showing the viewer) takes part of a core, the scheduler regularly
// deschedules one of the two training threads for a few milliseconds, and every region of a training step
// then waits for it even when the other thread could have done its share: stealing 0.4 of a core cost training
// 55 % instead of 20 %. Here chunks are claimed from a shared counter by the caller and by the pool's
// workers, and the caller returns once every chunk has run: a worker that wakes up late finds nothing left.
//
// Claims are validated against a generation number packed with the chunk counter (one 64-bit word), so a late
// worker can never run a chunk of a job other than the one whose description it read (see `work`).
//
// torch's own team. When the extension is built with OpenMP (Linux, where torch runs its ops on GNU OpenMP)
// and a job comes from the main thread with torch's thread count, the same chunk claims run on torch's OpenMP
// team instead of the pool's workers. After each of torch's parallel ops its workers spin for milliseconds
// (GOMP_SPINCOUNT) waiting for the next one; a pool worker then shares a core with a spinning thread, while a
// team worker picks the job up at once. In alternating runs that made the raster step up to 1.5x and training up
// to 14 % faster, and never slower in the median (docs/benchmark.md). The region's closing barrier does wait for
// a descheduled thread, which is what the pool avoids: a thread split (`set_num_threads`, the live viewer's) and
// other threads keep the pool.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#if defined(_OPENMP) && defined(__linux__)
#include <omp.h>
#include <sys/syscall.h>
#include <unistd.h>
#define METEGS_OPENMP_TEAM 1
#else
#define METEGS_OPENMP_TEAM 0
#endif

#if !defined(METEGS_PORTABLE) && (defined(__x86_64__) || defined(_M_X64))
#include <immintrin.h>
#define METEGS_PAUSE() _mm_pause()
// The caller's denormal mode (MXCSR flush-to-zero and denormals-are-zero), which every chunk of its job runs
// under: the trainer sets torch.set_flush_denormal(True) on its thread, and a worker started before that
// (or by a thread that did not) would otherwise run its chunks with slow denormal arithmetic (the projection
// backward of the benchmark scene: 1.3x slower).
#define METEGS_DENORMAL_MODE() (_mm_getcsr() & 0x8040u)
#define METEGS_SET_DENORMAL_MODE(m) _mm_setcsr((_mm_getcsr() & ~0x8040u) | (m))
#else
#define METEGS_PAUSE() std::this_thread::yield()
#define METEGS_DENORMAL_MODE() 0u
#define METEGS_SET_DENORMAL_MODE(m) ((void)(m))
#endif

namespace metegs {

// Threads of the metegs kernels called from this thread, when set (> 0) with set_num_threads; else torch's
// intra-op count of this thread. Lets a thread run torch's own ops on fewer threads than the kernels.
inline int64_t& thread_override() {
  static thread_local int64_t n = 0;
  return n;
}

inline int64_t num_threads() {
  const int64_t n = thread_override();
  return n > 0 ? n : std::max<int64_t>(1, at::get_num_threads());
}

// True when jobs from this thread run on torch's OpenMP team (see the top of this file): built with OpenMP, the
// process's main thread, no thread override, not inside an OpenMP region.
inline bool uses_openmp_team() {
#if METEGS_OPENMP_TEAM
  return thread_override() == 0 && !omp_in_parallel() && static_cast<pid_t>(syscall(SYS_gettid)) == getpid();
#else
  return false;
#endif
}

class TilePool {
 public:
  using Body = std::function<void(int64_t, int64_t)>;

  static TilePool& instance() {
    static TilePool* pool = new TilePool();  // never destroyed: workers may outlive static destruction order
    return *pool;
  }

  // Calls body(b, e) over [begin, end) in chunks of at least `grain`, on this thread and up to
  // num_threads() - 1 workers; returns when all chunks have run (rethrowing the first exception).
  void run(int64_t begin, int64_t end, int64_t grain, const Body& body) {
    const int64_t range = end - begin;
    if (range <= 0) return;
    const int64_t threads = num_threads();
    const int64_t by_grain = (range + std::max<int64_t>(grain, 1) - 1) / std::max<int64_t>(grain, 1);
    const int64_t nchunks = std::min<int64_t>({by_grain, threads * 8, int64_t(1) << 30});
    if (threads == 1 || nchunks <= 1 || inside()) {
      body(begin, end);
      return;
    }
    const bool team = uses_openmp_team();
    std::lock_guard<std::mutex> one_job(run_mu_);  // jobs from different threads take turns
    if (!team) ensure_workers(threads - 1);
    const uint32_t g = ++gen_;
    Slot& s = slots_[g & 1];
    s.body.store(&body, std::memory_order_relaxed);
    s.begin.store(begin, std::memory_order_relaxed);
    s.end.store(end, std::memory_order_relaxed);
    s.chunk.store((range + nchunks - 1) / nchunks, std::memory_order_relaxed);
    s.nchunks.store(nchunks, std::memory_order_relaxed);
    s.denormals.store(METEGS_DENORMAL_MODE(), std::memory_order_relaxed);
    done_.store(0, std::memory_order_relaxed);
    error_ = nullptr;
    ticket_.store(uint64_t(g) << 32, std::memory_order_release);  // publishes the slot
    {
      // the newest generation, on either path: a pool worker that joined a team's job while it was still
      // spinning must find no newer one when it goes to sleep (else its wait returns at once, for ever)
      std::lock_guard<std::mutex> lk(sleep_mu_);
      wake_gen_ = g;
    }
    if (team) {
      run_on_openmp_team(g, threads);
    } else {
      wake_.notify_all();
      inside() = true;
      work(g);
      inside() = false;
    }
    for (int spins = 0; done_.load(std::memory_order_acquire) < nchunks; ++spins) {
      if (spins < 4096) METEGS_PAUSE();
      else std::this_thread::yield();  // a chunk in flight on a descheduled worker: let it run
    }
    if (error_) std::rethrow_exception(error_);
  }

 private:
  struct Slot {  // one job's description; two slots so that the next job never overwrites the current one
    std::atomic<const Body*> body{nullptr};
    std::atomic<int64_t> begin{0}, end{0}, chunk{1}, nchunks{0};
    std::atomic<uint32_t> denormals{0};  // the caller's METEGS_DENORMAL_MODE()
  };

  static bool& inside() {
    static thread_local bool flag = false;  // nested calls run serially
    return flag;
  }

  // Claims and runs chunks of job `g` until none is left or a newer job has started. A claim is a CAS on
  // (generation, next chunk): it succeeds only while job g is current, and a slot is rewritten only two
  // generations later (after job g + 1 has completed), so the slot read before a successful claim is g's.
  void work(uint32_t g) {
    const Slot& s = slots_[g & 1];
    for (;;) {
      uint64_t t = ticket_.load(std::memory_order_acquire);
      if (uint32_t(t >> 32) != g) return;
      const int64_t idx = int64_t(t & 0xffffffffu);
      const int64_t nchunks = s.nchunks.load(std::memory_order_relaxed);
      if (idx >= nchunks) return;
      const Body* body = s.body.load(std::memory_order_relaxed);
      const int64_t begin = s.begin.load(std::memory_order_relaxed), end = s.end.load(std::memory_order_relaxed);
      const int64_t chunk = s.chunk.load(std::memory_order_relaxed);
      const uint32_t denormals = s.denormals.load(std::memory_order_relaxed);
      if (!ticket_.compare_exchange_weak(t, t + 1, std::memory_order_acq_rel)) continue;
      if (METEGS_DENORMAL_MODE() != denormals) METEGS_SET_DENORMAL_MODE(denormals);
      const int64_t b = begin + idx * chunk, e = std::min(end, b + chunk);
      if (b < e) {
        try {
          (*body)(b, e);
        } catch (...) {
          std::lock_guard<std::mutex> lk(error_mu_);
          if (!error_) error_ = std::current_exception();
        }
      }
      done_.fetch_add(1, std::memory_order_release);
    }
  }

  // Job g's chunk claims on every thread of an OpenMP team of `threads` (torch's, on the main thread); a team thread
  // gets back its own denormal mode afterwards, as it runs torch's ops under it.
  void run_on_openmp_team(uint32_t g, int64_t threads) {
#if METEGS_OPENMP_TEAM
#pragma omp parallel num_threads(static_cast<int>(threads))
    {
      const uint32_t mode = METEGS_DENORMAL_MODE();
      inside() = true;
      work(g);
      inside() = false;
      if (METEGS_DENORMAL_MODE() != mode) METEGS_SET_DENORMAL_MODE(mode);
    }
#else
    (void)threads;
    work(g);
#endif
  }

  void ensure_workers(int64_t wanted) {
    while (int64_t(workers_.size()) < wanted) {
      workers_.emplace_back([this] { worker_loop(); });
      workers_.back().detach();
    }
  }

  void worker_loop() {
    inside() = true;
    uint32_t seen = uint32_t(ticket_.load(std::memory_order_acquire) >> 32);
    for (;;) {
      uint32_t g = uint32_t(ticket_.load(std::memory_order_acquire) >> 32);
      for (int spins = 0; g == seen; ++spins) {  // spin briefly (jobs come in bursts), then sleep
        if (spins < 2048) {
          METEGS_PAUSE();
        } else {
          std::unique_lock<std::mutex> lk(sleep_mu_);
          wake_.wait(lk, [&] { return wake_gen_ != seen; });
          spins = 0;
        }
        g = uint32_t(ticket_.load(std::memory_order_acquire) >> 32);
      }
      seen = g;
      work(g);
    }
  }

  std::mutex run_mu_, sleep_mu_, error_mu_;
  std::condition_variable wake_;
  uint32_t wake_gen_ = 0;  // guarded by sleep_mu_
  uint32_t gen_ = 0;       // guarded by run_mu_
  Slot slots_[2];
  std::atomic<uint64_t> ticket_{0};
  std::atomic<int64_t> done_{0};
  std::exception_ptr error_;
  std::vector<std::thread> workers_;
};

// Drop-in for at::parallel_for(begin, end, grain, f) on the pool above.
template <typename F>
inline void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  TilePool::instance().run(begin, end, grain, TilePool::Body(std::cref(f)));
}

}  // namespace metegs
