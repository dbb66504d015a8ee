/* Forced into liblsl's C++ compiles (see .cargo/config.toml). The Boost that liblsl 1.14
 * bundles tests `#if PTHREAD_STACK_MIN > 0`; since glibc 2.34 PTHREAD_STACK_MIN is a call
 * to sysconf(), which the preprocessor cannot evaluate. Boost only uses it as a lower bound
 * for a thread's stack size, and 128 KiB is at least every architecture's minimum (x86-64's
 * is 16 KiB, aarch64's 128 KiB). */
#include <limits.h>
#include <pthread.h>
#undef PTHREAD_STACK_MIN
#define PTHREAD_STACK_MIN 131072
