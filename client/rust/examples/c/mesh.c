/* mesh.c: a mesh collider (protocol 1.8) over the drape C ABI (include/drape.h): a 9x9 cape
 * submitted (drape_submit_grid_ex) with its own mesh collider, a closed 0.4 m box 0.3 m below
 * it, and a 2 cm thickness kept from it, falls onto the box;
 * every state received is checked for vertices inside the box (0 expected); then the box is
 * moved 5 cm sideways by a pose (the per-tick change, drape_cloth_move_mesh_collider) and
 * checked again, and a bad mesh is refused before sending with the triangle named. Exits 1 on
 * any vertex inside or an unexpected error; a server older than 1.8 is reported and skipped.
 * Usage: mesh [ENDPOINT] [SECONDS]   (default tcp/127.0.0.1:7447, 2) */
#include "drape.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define HALF 0.2
#define COLS 9u

static int check(int32_t rc, const char *what) {
    if (rc != DRAPE_OK) {
        char msg[512];
        drape_last_error(msg, sizeof msg);
        fprintf(stderr, "%s failed: %s (%d): %s\n", what, drape_error_name(rc), rc, msg);
        exit(1);
    }
    return rc;
}

/* A closed box of half extent HALF about the origin, its triangles counter-clockwise seen
 * from outside: vertex i at ((i & 1), (i >> 1) & 1, (i >> 2) & 1) scaled to +-HALF. */
static const uint32_t BOX_TRIANGLES[36] = {
    0, 4, 6, 0, 6, 2, /* -x */ 1, 3, 7, 1, 7, 5, /* +x */
    0, 1, 5, 0, 5, 4, /* -y */ 2, 6, 7, 2, 7, 3, /* +y */
    0, 2, 3, 0, 3, 1, /* -z */ 4, 5, 7, 4, 7, 6, /* +z */
};

static void box_vertices(float v[24]) {
    for (int i = 0; i < 8; i++)
        for (int k = 0; k < 3; k++)
            v[3 * i + k] = (float)((((i >> k) & 1) ? 1.0 : -1.0) * HALF);
}

/* Vertices more than 1 mm inside the box centred at c. */
static int inside(const float *p, uint32_t n, const double c[3]) {
    int count = 0;
    for (uint32_t i = 0; i < n; i++) {
        int in = 1;
        for (int k = 0; k < 3; k++)
            in &= fabs(p[3 * i + k] - c[k]) < HALF - 1e-3;
        count += in;
    }
    return count;
}

/* Reads states for `frames` waits of up to 50 ms from tick `from` on: the most vertices inside
 * the box at c in any of them; *states counts them. */
static int watch(DrapeCloth *cape, float *pos, uint32_t n, int frames, uint64_t from, const double c[3], int *states) {
    int worst = 0;
    *states = 0;
    for (int f = 0; f < frames; f++) {
        DrapeStateInfo info;
        int32_t rc = drape_cloth_wait_state(cape, pos, 3 * (size_t)n, NULL, 0, 50, &info);
        if (rc == DRAPE_NO_DATA)
            continue;
        check(rc, "drape_cloth_wait_state");
        if (info.tick < from)
            continue;
        int in = inside(pos, n, c);
        worst = in > worst ? in : worst;
        (*states)++;
    }
    return worst;
}

int main(int argc, char **argv) {
    const char *endpoint = argc > 1 ? argv[1] : "tcp/127.0.0.1:7447";
    double seconds = argc > 2 ? atof(argv[2]) : 2.0;
    DrapeClientOptions opts = {0};
    opts.connect = endpoint;
    opts.timeout_ms = 30000;
    DrapeClient *client = NULL;
    check(drape_client_open(&opts, &client), "drape_client_open");
    DrapeServerInfo si;
    check(drape_client_server_info(client, NULL, &si), "drape_client_server_info");
    if (si.version_major == 1 && si.version_minor < 8) {
        printf("server %s speaks %u.%u: no mesh colliders before 1.8, skipped\n", si.server, si.version_major, si.version_minor);
        drape_client_close(client, true);
        return 0;
    }

    float box[24];
    box_vertices(box);
    double centre[3] = {0.0, 1.0, 0.0};
    DrapeMeshCollider mesh = {0};
    mesh.vertices = box;
    mesh.vertex_count = 8;
    mesh.triangles = BOX_TRIANGLES;
    mesh.triangle_count = 12;
    memcpy(mesh.position, centre, sizeof centre); /* rotation all 0: the identity */

    /* a bad mesh first: triangle 2 repeats a vertex, refused here with the triangle named */
    uint32_t bad_triangles[36];
    memcpy(bad_triangles, BOX_TRIANGLES, sizeof bad_triangles);
    bad_triangles[7] = bad_triangles[6];
    DrapeMeshCollider bad = mesh;
    bad.triangles = bad_triangles;
    DrapeGrid grid = {COLS, COLS, 0.6, 0.6, false, {-0.3, 1.0 + HALF + 0.3, -0.3}};
    DrapeMaterial material = {0};
    material.fields = DRAPE_MATERIAL_FRICTION;
    material.friction = 0.3;
    DrapeClothOptions copts = {0};
    copts.substeps = 2;
    copts.material = &material;
    DrapeSubmitExtras extras = {0};
    extras.thickness = 0.02;
    extras.mesh_collider = &bad;
    DrapeCloth *cape = NULL;
    int32_t rc = drape_submit_grid_ex(client, &grid, &copts, &extras, &cape);
    char msg[512];
    drape_last_error(msg, sizeof msg);
    if (rc != DRAPE_E_INVALID_VALUE || !strstr(msg, "triangle 2")) {
        fprintf(stderr, "a degenerate triangle was not refused as expected: %s (%d): %s\n", drape_error_name(rc), rc, msg);
        return 1;
    }
    printf("bad mesh refused: %s\n", msg);

    extras.mesh_collider = &mesh;
    check(drape_submit_grid_ex(client, &grid, &copts, &extras, &cape), "drape_submit_grid_ex");
    uint32_t n = drape_cloth_vertex_count(cape);
    float *pos = malloc(sizeof(float) * 3 * n);
    int states = 0;
    int frames = (int)(seconds * 20);
    int worst = watch(cape, pos, n, frames, 0, centre, &states);
    float low = pos[1];
    for (uint32_t i = 1; i < n; i++)
        low = pos[3 * i + 1] < low ? pos[3 * i + 1] : low;
    printf("dropped on the box: %d states, at most %d vertices inside, lowest y %.3f\n", states, worst, low);
    int failed = worst > 0 || states < 10 || low < 0.5f;

    double moved[3] = {0.05, 1.0, 0.0};
    uint64_t tick = 0;
    check(drape_cloth_move_mesh_collider(cape, moved, NULL, true, &tick), "drape_cloth_move_mesh_collider");
    worst = watch(cape, pos, n, frames / 2, tick, moved, &states);
    printf("box moved 5 cm at tick %llu: %d states, at most %d vertices inside\n", (unsigned long long)tick, states, worst);
    failed |= worst > 0;

    DrapeMeshCollider removal = {0};
    removal.remove = true;
    check(drape_cloth_set_mesh_collider(cape, &removal, true, NULL), "drape_cloth_set_mesh_collider (remove)");
    check(drape_cloth_remove(cape, NULL), "drape_cloth_remove");
    drape_cloth_free(cape);
    free(pos);
    drape_client_close(client, true);
    printf(failed ? "FAILED\n" : "ok\n");
    return failed;
}
