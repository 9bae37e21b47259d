/* cape.c: a small game loop in C over the drape C ABI (include/drape.h): submit a 16x12 cape
 * pinned at its two top corners, move the pins every frame without waiting, read each new
 * state into a caller-owned buffer and print what arrives; then render one second at 144 Hz
 * with drape_cloth_sample (the last two states interpolated a tick behind the newest) and count
 * the frames where the cape moved. Build: examples/c/build.sh.
 * Usage: cape [ENDPOINT] [FRAMES]   (default tcp/127.0.0.1:7447, 120) */
#define _POSIX_C_SOURCE 199309L
#include "drape.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static int check(int32_t rc, const char *what) {
    if (rc != DRAPE_OK) {
        char msg[512];
        drape_last_error(msg, sizeof msg);
        fprintf(stderr, "%s failed: %s (%d): %s\n", what, drape_error_name(rc), rc, msg);
        exit(1);
    }
    return rc;
}

int main(int argc, char **argv) {
    const char *endpoint = argc > 1 ? argv[1] : "tcp/127.0.0.1:7447";
    int frames = argc > 2 ? atoi(argv[2]) : 120;
    printf("%s\n", drape_version());

    DrapeClientOptions opts = {0};
    opts.connect = endpoint;
    opts.timeout_ms = 30000;
    DrapeClient *client = NULL;
    check(drape_client_open(&opts, &client), "drape_client_open");
    char server[80];
    check(drape_client_server_id(client, server, sizeof server), "drape_client_server_id");
    printf("using server %s\n", server);

    const uint32_t cols = 16, rows = 12;
    DrapeGrid grid = {cols, rows, 0.8, 1.0, true, {-0.4, 1.8, 0.0}};
    uint32_t pins[2] = {0, cols - 1};
    DrapeClothOptions copts = {0};
    copts.pinned = pins;
    copts.pinned_count = 2;
    copts.encoding = 1; /* float16 */
    DrapeCloth *cape = NULL;
    check(drape_submit_grid(client, &grid, &copts, &cape), "drape_submit_grid");
    uint32_t n = drape_cloth_vertex_count(cape);
    char id[80];
    drape_cloth_id(cape, id, sizeof id);
    printf("cape %s: %u vertices, %u triangles\n", id, n, drape_cloth_triangle_count(cape));

    /* Protocol 1.2: switch wind on without touching the other features (a 1.1 server is refused
     * client-side with INVALID_VALUE: it would ignore the change). */
    uint32_t features = 0;
    int32_t frc = drape_cloth_change_features(cape, DRAPE_FEATURE_WIND, 0, true, NULL, &features);
    if (frc == DRAPE_OK && features == DRAPE_FEATURES_UNKNOWN)
        printf("wind on; the server did not report the resulting features\n");
    else if (frc == DRAPE_OK)
        printf("wind on; features now 0x%x\n", features);
    else if (frc == DRAPE_E_INVALID_VALUE)
        printf("no feature change: the server is older than protocol 1.2\n");
    else
        check(frc, "drape_cloth_change_features");

    float *positions = malloc(sizeof(float) * 3 * n); /* one buffer, reused every frame */
    int received = 0;
    for (int frame = 0; frame < frames; frame++) {
        float a = frame * 0.05f, dx = 0.3f * cosf(a), dz = 0.3f * sinf(a);
        float targets[6] = {-0.4f + dx, 1.8f, dz, 0.4f + dx, 1.8f, dz};
        check(drape_cloth_move_pins(cape, pins, 2, targets, false, NULL), "drape_cloth_move_pins");
        DrapeStateInfo info;
        int32_t rc = drape_cloth_wait_state(cape, positions, 3 * (size_t)n, NULL, 0, 100, &info);
        if (rc == DRAPE_OK) {
            received++;
            const float *hem = positions + 3 * ((rows - 1) * cols + cols / 2);
            if (frame % 20 == 0)
                printf("frame %3d: tick %llu hem at (%+.3f, %+.3f, %+.3f)\n", frame, (unsigned long long)info.tick,
                       hem[0], hem[1], hem[2]);
        } else if (rc != DRAPE_NO_DATA) {
            check(rc, "drape_cloth_wait_state");
        }
        DrapeEvent ev;
        while (drape_client_poll_event(client, 0, &ev) == DRAPE_OK)
            if (ev.kind != DRAPE_EVENT_SERVER_FOUND)
                printf("event %d (%s): %s\n", ev.kind, drape_error_name(ev.code), ev.message);
    }
    /* Render at 144 Hz, faster than the server's 60 Hz states: sampled at each frame's time, the
     * cape moves in every frame (read raw, it would repeat a state in most frames). */
    float *previous = calloc(3 * (size_t)n, sizeof(float));
    int moved = 0, sampled = 0;
    for (int frame = 0; frame < 144; frame++) {
        float a = (frames + frame * 60 / 144) * 0.05f, dx = 0.3f * cosf(a), dz = 0.3f * sinf(a);
        float targets[6] = {-0.4f + dx, 1.8f, dz, 0.4f + dx, 1.8f, dz};
        check(drape_cloth_move_pins(cape, pins, 2, targets, false, NULL), "drape_cloth_move_pins");
        /* now (0), one tick behind the newest state (-1), interpolated (not extrapolated) */
        int32_t rc = drape_cloth_sample(cape, 0, -1, false, positions, 3 * (size_t)n);
        if (rc == DRAPE_OK) {
            moved += sampled++ > 0 && memcmp(previous, positions, sizeof(float) * 3 * n) != 0;
            memcpy(previous, positions, sizeof(float) * 3 * n);
        } else if (rc != DRAPE_NO_DATA) {
            check(rc, "drape_cloth_sample");
        }
        struct timespec ts = {0, 1000000000L / 144};
        nanosleep(&ts, NULL);
    }
    printf("144 Hz for 1 s: the sampled cape moved in %d of %d frames\n", moved, sampled > 0 ? sampled - 1 : 0);
    free(previous);
    uint64_t last = 0;
    check(drape_cloth_remove(cape, &last), "drape_cloth_remove");
    printf("%d frames: %d states read; removed, last tick %llu\n", frames, received, (unsigned long long)last);
    drape_cloth_free(cape);
    drape_client_close(client, true);
    free(positions);
    return received > 0 ? 0 : 1;
}
