/* A wall clock a test can step under a real process (tests/support/wall_clock.py): preloaded (LD_PRELOAD), it adds
   the offset in the file $CELLCTL_WALL_OFFSET_FILE (whole seconds, as text; read at every call, so rewriting it steps
   the clock at once, as an NTP step would) to the wall clock, and leaves every other clock alone: the monotonic
   one, and every wait and sleep, which run on it. (libfaketime 0.9.10, Debian 12's, cannot leave the monotonic clock
   alone for Python 3.11: its time.sleep fails with EINVAL, libfaketime issue #426.) */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <fcntl.h>
#include <stdlib.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

static long offset_s(void)
{
    const char *path = getenv("CELLCTL_WALL_OFFSET_FILE");
    char text[32] = {0};
    int fd = path ? open(path, O_RDONLY | O_CLOEXEC) : -1;
    if (fd < 0)
        return 0;
    ssize_t n = read(fd, text, sizeof text - 1);
    close(fd);
    return n > 0 ? strtol(text, NULL, 10) : 0;
}

int clock_gettime(clockid_t clock, struct timespec *tp)
{
    static int (*real)(clockid_t, struct timespec *);
    if (!real)
        real = (int (*)(clockid_t, struct timespec *))dlsym(RTLD_NEXT, "clock_gettime");
    int result = real(clock, tp);
    if (result == 0 && (clock == CLOCK_REALTIME || clock == CLOCK_REALTIME_COARSE))
        tp->tv_sec += offset_s();
    return result;
}

int gettimeofday(struct timeval *restrict tv, void *restrict tz)
{
    static int (*real)(struct timeval *restrict, void *restrict);
    if (!real)
        real = (int (*)(struct timeval *restrict, void *restrict))dlsym(RTLD_NEXT, "gettimeofday");
    struct timeval *volatile given = tv; /* NULL is allowed (only the time zone asked), though glibc says nonnull */
    int result = real(tv, tz);
    if (result == 0 && given)
        given->tv_sec += offset_s();
    return result;
}

time_t time(time_t *out)
{
    struct timespec now;
    clock_gettime(CLOCK_REALTIME, &now);
    if (out)
        *out = now.tv_sec;
    return now.tv_sec;
}
