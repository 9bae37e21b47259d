/* engine.c: a C game loop over the drape C ABI (include/drape.h) that never blocks its game
 * thread: N bundled 32x32 capes (default 16) submitted asynchronously with colliders (a body
 * capsule and a head sphere), wind and a material, their pins moved every frame along a circle
 * with drape_move_pins_many (not waited for), every state read (each cape keeps a small queue:
 * read until DRAPE_NO_DATA), a feature switched on mid-run with drape_cloth_control_async, and
 * every state accounted for at the end (read + replaced + missed + unread == ticks).
 *
 * Usage: engine ENDPOINT [SECONDS=10] [CAPES=16] [QUEUE=8]
 * Prints one "engine:" summary line (states, ticks, CPU, the slowest call on the game thread)
 * and exits 0 when every cape went live, states were read and every counter identity holds.
 * Build: examples/c/build.sh (or CMake, see CMakeLists.txt next to it).
 * With -DDRAPE_LEGACY it is the same loop written against the 0.3.0 header (blocking submits,
 * no queue, one read per frame, no colliders / wind / material): the CPU baseline. */
#define _GNU_SOURCE /* RUSAGE_THREAD */
#include "drape.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>

#define MAX_CAPES 64
#define COLS 32
#define ROWS 32
#define NPINS 4

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static double cpu_s(void) {
    struct rusage ru;
    getrusage(RUSAGE_SELF, &ru);
    return ru.ru_utime.tv_sec + ru.ru_utime.tv_usec * 1e-6 + ru.ru_stime.tv_sec + ru.ru_stime.tv_usec * 1e-6;
}

static void die(int32_t rc, const char *what) {
    char msg[512];
    drape_last_error(msg, sizeof msg);
    fprintf(stderr, "engine: %s failed: %s (%d): %s\n", what, drape_error_name(rc), rc, msg);
    exit(1);
}

/* The game thread's API calls: how many, how many blocked (the thread gave up the CPU during
 * the call: a voluntary context switch, i.e. it waited on a lock, a condition or the network;
 * being preempted on a busy machine is involuntary and not counted), and the slowest by wall
 * clock (which a loaded machine inflates). */
static long calls = 0, blocked_calls = 0;
static double slowest = 0;
static const char *slowest_what = "", *blocked_what = "";
static long voluntary_switches(void) {
    struct rusage ru;
    getrusage(RUSAGE_THREAD, &ru);
    return ru.ru_nvcsw;
}
#define TIMED(what, expr)                                              \
    ({                                                                 \
        long v0_ = voluntary_switches();                               \
        double t0_ = now_s();                                          \
        int32_t rc_ = (expr);                                          \
        double dt_ = now_s() - t0_;                                    \
        calls++;                                                       \
        if (voluntary_switches() != v0_) { blocked_calls++; blocked_what = (what); } \
        if (dt_ > slowest) { slowest = dt_; slowest_what = (what); }   \
        rc_;                                                           \
    })

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: engine ENDPOINT [SECONDS=10] [CAPES=16] [QUEUE=8]\n");
        return 2;
    }
    double seconds = argc > 2 ? atof(argv[2]) : 10.0;
    int ncapes = argc > 3 ? atoi(argv[3]) : 16;
    int queue = argc > 4 ? atoi(argv[4]) : 8;
    if (ncapes < 1 || ncapes > MAX_CAPES) ncapes = 16;

    DrapeClientOptions opts = {0};
    opts.connect = argv[1];
    opts.timeout_ms = 30000;
    DrapeClient *client = NULL;
    int32_t rc = drape_client_open(&opts, &client); /* load time: fails at once with no server */
    if (rc != DRAPE_OK) die(rc, "drape_client_open");
    double tick_rate = 60;
#ifndef DRAPE_LEGACY
    DrapeServerInfo si;
    if ((rc = drape_client_server_info(client, NULL, &si)) != DRAPE_OK) die(rc, "drape_client_server_info");
    tick_rate = si.tick_rate;
    printf("server %s speaks %u.%u at %.0f Hz (max %llu colliders)\n", si.server, si.version_major, si.version_minor,
           si.tick_rate, (unsigned long long)si.max_colliders);
#endif

    uint32_t pins[NPINS] = {0, COLS / 3, 2 * COLS / 3, COLS - 1};
    DrapeClothOptions co = {0};
    co.pinned = pins;
    co.pinned_count = NPINS;
    co.encoding = 2; /* quant16 */
    co.bundle = true;
#ifndef DRAPE_LEGACY
    double wind[3] = {1.5, 0.0, 0.5};
    DrapeMaterial mat = {0};
    mat.fields = DRAPE_MATERIAL_MASS | DRAPE_MATERIAL_DAMPING | DRAPE_MATERIAL_FRICTION;
    mat.mass = 0.6;
    mat.damping = 0.02;
    mat.friction = 0.3;
    co.wind = wind;
    co.material = &mat;
    co.features = DRAPE_FEATURE_TETHERS | DRAPE_FEATURE_COLLIDERS | DRAPE_FEATURE_WIND;
    co.queue_size = (uint32_t)queue;
    co.retry_ms = 60000; /* refused while the server admits others: retried in the background */
#endif

    DrapeCloth *capes[MAX_CAPES];
    int live[MAX_CAPES] = {0};
    double x0[MAX_CAPES];
    for (int i = 0; i < ncapes; i++) {
        x0[i] = 2.0 * i;
        /* a vertical 0.6 x 0.9 m cape hanging at a character's shoulders */
        DrapeGrid grid = {COLS, ROWS, 0.6, 0.9, true, {x0[i] - 0.3, 1.5, -0.15}};
#ifndef DRAPE_LEGACY
        /* the character: a body capsule and a head sphere, in the same world frame */
        DrapeCollider body[2] = {
            {DRAPE_COLLIDER_CAPSULE, {x0[i], 0.6, 0.0}, {x0[i], 1.4, 0.0}, 0.22, 0},
            {DRAPE_COLLIDER_SPHERE, {x0[i], 1.65, 0.0}, {0, 0, 0}, 0.12, 0},
        };
        co.colliders = body;
        co.collider_count = 2;
        rc = TIMED("drape_submit_grid_async", drape_submit_grid_async(client, &grid, &co, &capes[i]));
        if (rc != DRAPE_OK) die(rc, "drape_submit_grid_async");
#else
        if ((rc = drape_submit_grid(client, &grid, &co, &capes[i])) != DRAPE_OK) die(rc, "drape_submit_grid");
        live[i] = 1;
#endif
    }
    uint32_t n = COLS * ROWS;
    float *positions = malloc(sizeof(float) * 3 * n); /* one buffer, reused */
    float *targets = malloc(sizeof(float) * 3 * NPINS * ncapes);
    const DrapeCloth *movers[MAX_CAPES];
    long states = 0, frames = 0, events = 0, submitted = 0;
    uint64_t feature_request = 0;
    int feature_done = 0;
    double frame_dt = 1.0 / 60.0;
    /* The measured SECONDS start once every cape is live (submissions refused while the server
     * admits others are retried in the background: up to 90 s of frames before that). */
    double t_begin = now_s(), t_start = t_begin, cpu_start = cpu_s();
    int measuring = 0;
#ifdef DRAPE_LEGACY
    measuring = 1;
#endif
    double next_frame = t_begin;
    while (measuring ? now_s() - t_start < seconds : now_s() - t_begin < 90) {
        if (!measuring && submitted == ncapes) {
            measuring = 1;
            t_start = now_s();
            cpu_start = cpu_s();
            calls = blocked_calls = 0;
            slowest = 0;
            frames = 1;
        }
        frames++;
        /* events: asynchronous submissions and controls complete here */
        DrapeEvent ev;
        while (TIMED("drape_client_poll_event", drape_client_poll_event(client, 0, &ev)) == DRAPE_OK) {
            events++;
#ifndef DRAPE_LEGACY
            if (ev.kind == DRAPE_EVENT_SUBMITTED) {
                for (int i = 0; i < ncapes; i++)
                    if (drape_cloth_handle(capes[i]) == ev.handle) live[i] = 1;
                submitted++;
                continue;
            } else if (ev.kind == DRAPE_EVENT_REQUEST_DONE && ev.request == feature_request) {
                feature_done = 1;
                printf("frame %ld: normals on for %s from tick %llu, features 0x%x\n", frames, ev.cloth,
                       (unsigned long long)ev.tick, ev.features);
                continue;
            } else if (ev.kind == DRAPE_EVENT_SUBMIT_FAILED) {
                printf("submit failed (%s): %s\n", drape_error_name(ev.code), ev.message);
                return 1;
            }
#endif
            if (ev.kind != DRAPE_EVENT_SERVER_FOUND)
                printf("event %d (%s) cloth %s: %s\n", ev.kind, drape_error_name(ev.code), ev.cloth, ev.message);
        }
        /* pins of every live cape along a circle, one call, not waited for */
        double a = frames * (2 * 3.14159265358979 / 120.0);
        int m = 0;
        for (int i = 0; i < ncapes; i++) {
            if (!live[i]) continue;
            for (int p = 0; p < NPINS; p++) {
                float *t = targets + 3 * (m * NPINS + p);
                t[0] = (float)(x0[i] - 0.3 + 0.6 * pins[p] / (COLS - 1) + 0.1 * cos(a));
                t[1] = 1.5f;
                t[2] = (float)(-0.15 + 0.1 * sin(a));
            }
            movers[m++] = capes[i];
        }
        if (m > 0) {
            rc = TIMED("drape_move_pins_many",
                       drape_move_pins_many(client, movers, (size_t)m, pins, NPINS, targets, false, NULL, NULL));
            if (rc != DRAPE_OK) die(rc, "drape_move_pins_many");
        }
        /* every state that arrived since the last frame */
        for (int i = 0; i < ncapes; i++) {
            if (!live[i]) continue;
            DrapeStateInfo info;
#ifndef DRAPE_LEGACY
            while ((rc = TIMED("drape_cloth_read_state",
                               drape_cloth_read_state(capes[i], positions, 3 * (size_t)n, NULL, 0, &info))) == DRAPE_OK)
                states++;
#else
            if ((rc = drape_cloth_read_state(capes[i], positions, 3 * (size_t)n, NULL, 0, &info)) == DRAPE_OK) states++;
#endif
            if (rc != DRAPE_OK && rc != DRAPE_NO_DATA) die(rc, "drape_cloth_read_state");
        }
#ifndef DRAPE_LEGACY
        /* one second in: switch normals on for cape 0 without waiting (it blocked 800 ms waited) */
        if (feature_request == 0 && measuring && now_s() - t_start > 1.0) {
            DrapeControl ctl = {0};
            ctl.features_add = DRAPE_FEATURE_NORMALS;
            rc = TIMED("drape_cloth_control_async", drape_cloth_control_async(capes[0], &ctl, &feature_request));
            if (rc != DRAPE_OK) die(rc, "drape_cloth_control_async");
        }
#endif
        next_frame += frame_dt;
        double sleep_s = next_frame - now_s();
        if (sleep_s > 0) {
            struct timespec ts = {(time_t)sleep_s, (long)((sleep_s - (time_t)sleep_s) * 1e9)};
            nanosleep(&ts, NULL);
        } else {
            next_frame = now_s();
        }
    }
    double wall = now_s() - t_start, cpu = cpu_s() - cpu_start;
    int ok = 1;
#ifndef DRAPE_LEGACY
    uint64_t rec = 0, read = 0, repl = 0, miss = 0, unread = 0, ticks = 0;
    for (int i = 0; i < ncapes; i++) {
        DrapeStateCounters k;
        if ((rc = drape_cloth_counters(capes[i], &k)) != DRAPE_OK) die(rc, "drape_cloth_counters");
        if (k.read + k.replaced + k.missed + k.unread != k.ticks || k.received != k.read + k.replaced + k.unread) {
            printf("cape %d: counters do not add up: read %llu replaced %llu missed %llu unread %llu ticks %llu\n", i,
                   (unsigned long long)k.read, (unsigned long long)k.replaced, (unsigned long long)k.missed,
                   (unsigned long long)k.unread, (unsigned long long)k.ticks);
            ok = 0;
        }
        if (k.read == 0) printf("engine: no state read of cape %d\n", i), ok = 0;
        rec += k.received, read += k.read, repl += k.replaced, miss += k.missed, unread += k.unread, ticks += k.ticks;
    }
    if (submitted != ncapes) printf("engine: only %ld of %d capes went live\n", submitted, ncapes), ok = 0;
    if (!feature_done) printf("engine: the asynchronous feature change did not complete\n"), ok = 0;
    printf("engine: %d capes, %.1f s, %ld frames, %.1f Hz server; states: received %llu read %llu replaced %llu "
           "missed %llu unread %llu ticks %llu (read+replaced+missed+unread %s ticks); cpu %.2f s = %.1f %% of one core; "
           "%ld game-thread calls, %ld blocked%s%s%s, slowest %.3f ms (%s); %ld events\n",
           ncapes, wall, frames, tick_rate, (unsigned long long)rec, (unsigned long long)read, (unsigned long long)repl,
           (unsigned long long)miss, (unsigned long long)unread, (unsigned long long)ticks,
           read + repl + miss + unread == ticks ? "==" : "!=", cpu, 100 * cpu / wall, calls, blocked_calls,
           blocked_calls ? " (last: " : "", blocked_calls ? blocked_what : "", blocked_calls ? ")" : "", slowest * 1e3, slowest_what, events);
#else
    printf("engine (legacy): %d capes, %.1f s, %ld frames; states read %ld; cpu %.2f s = %.1f %% of one core\n", ncapes, wall,
           frames, states, cpu, 100 * cpu / wall);
    if (states == 0) ok = 0;
#endif
    for (int i = 0; i < ncapes; i++) {
        drape_cloth_remove(capes[i], NULL); /* after the loop: remove waits for the reply */
        drape_cloth_free(capes[i]);
    }
    drape_client_close(client, true);
    free(positions);
    free(targets);
    return ok ? 0 : 1;
}
