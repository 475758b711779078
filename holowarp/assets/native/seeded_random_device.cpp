// A seedable std::random_device for fTetWild (holowarp.repeatable).
//
// fTetWild (through pytetwild) seeds its random choices from std::random_device, so two
// tetrahedralisations of one surface differ. Loaded with RTLD_GLOBAL before pytetwild's
// extension, this library's definition of std::random_device::_M_getval() is the one the
// extension binds to: every draw then comes from a SplitMix64 stream that
// holowarp_seed_random_device() resets. Code loaded earlier keeps libstdc++'s own device.
// fTetWild also calls libc's rand(), whose state lives on from call to call in a process,
// so the same function seeds it (srand) as well.
#include <cstdint>
#include <cstdlib>
#include <mutex>
#include <random>

namespace {
std::mutex guard_mutex;
std::uint64_t stream = 0;
std::uint64_t draws = 0;
}  // namespace

extern "C" void holowarp_seed_random_device(std::uint64_t seed) {
    std::lock_guard<std::mutex> guard(guard_mutex);
    stream = seed;
    draws = 0;
    std::srand(static_cast<unsigned int>(seed ^ (seed >> 32)));
}

extern "C" std::uint64_t holowarp_random_device_draws() {
    std::lock_guard<std::mutex> guard(guard_mutex);
    return draws;
}

unsigned int std::random_device::_M_getval() {
    std::lock_guard<std::mutex> guard(guard_mutex);
    ++draws;
    std::uint64_t z = (stream += 0x9E3779B97F4A7C15ULL);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return static_cast<unsigned int>((z ^ (z >> 31)) >> 32);
}
