/* layout.c: prints the size of every struct of drape.h and the offset of each field, one
 * "Name size" / "Name.field offset" per line, for the C# layout test (Tests.cs). */
#include "drape.h"

#include <stddef.h>
#include <stdio.h>

#define S(T) printf(#T " %zu\n", sizeof(T))
#define F(T, f) printf(#T "." #f " %zu\n", offsetof(T, f))

int main(void) {
    S(DrapeClientOptions); F(DrapeClientOptions, connect); F(DrapeClientOptions, server_id); F(DrapeClientOptions, client_id);
    F(DrapeClientOptions, namespace_); F(DrapeClientOptions, timeout_ms); F(DrapeClientOptions, no_failover); F(DrapeClientOptions, lazy);
    S(DrapeEvent); F(DrapeEvent, kind); F(DrapeEvent, code); F(DrapeEvent, handle); F(DrapeEvent, server); F(DrapeEvent, cloth);
    F(DrapeEvent, old_cloth); F(DrapeEvent, message); F(DrapeEvent, old_server); F(DrapeEvent, resumed_tick); F(DrapeEvent, reason);
    F(DrapeEvent, resumed); F(DrapeEvent, kept); F(DrapeEvent, request); F(DrapeEvent, tick); F(DrapeEvent, features);
    S(DrapeGrid); F(DrapeGrid, cols); F(DrapeGrid, rows); F(DrapeGrid, width); F(DrapeGrid, height); F(DrapeGrid, vertical); F(DrapeGrid, origin);
    S(DrapeClothOptions); F(DrapeClothOptions, pinned); F(DrapeClothOptions, pinned_count); F(DrapeClothOptions, encoding);
    F(DrapeClothOptions, normals); F(DrapeClothOptions, bundle); F(DrapeClothOptions, quality); F(DrapeClothOptions, gravity);
    F(DrapeClothOptions, wind); F(DrapeClothOptions, material); F(DrapeClothOptions, colliders); F(DrapeClothOptions, collider_count);
    F(DrapeClothOptions, features); F(DrapeClothOptions, iterations); F(DrapeClothOptions, substeps); F(DrapeClothOptions, queue_size);
    F(DrapeClothOptions, retry_ms);
    S(DrapeStateInfo); F(DrapeStateInfo, tick); F(DrapeStateInfo, server_time_ns); F(DrapeStateInfo, receive_time_ns);
    F(DrapeStateInfo, vertex_count); F(DrapeStateInfo, flags); F(DrapeStateInfo, encoding); F(DrapeStateInfo, has_normals);
    F(DrapeStateInfo, reset); F(DrapeStateInfo, bounds_min); F(DrapeStateInfo, bounds_max);
    S(DrapeCollider); F(DrapeCollider, kind); F(DrapeCollider, a); F(DrapeCollider, b); F(DrapeCollider, radius); F(DrapeCollider, offset);
    S(DrapeMaterial); F(DrapeMaterial, fields); F(DrapeMaterial, mass); F(DrapeMaterial, stiffness); F(DrapeMaterial, compliance);
    F(DrapeMaterial, damping); F(DrapeMaterial, friction); F(DrapeMaterial, drag); F(DrapeMaterial, lift); F(DrapeMaterial, air_density);
    F(DrapeMaterial, tether_limit);
    S(DrapeControl); F(DrapeControl, gravity); F(DrapeControl, wind); F(DrapeControl, material); F(DrapeControl, colliders);
    F(DrapeControl, collider_count); F(DrapeControl, set_colliders); F(DrapeControl, features_add); F(DrapeControl, features_remove);
    F(DrapeControl, iterations); F(DrapeControl, substeps); F(DrapeControl, quality); F(DrapeControl, set_state); F(DrapeControl, encoding);
    F(DrapeControl, normals); F(DrapeControl, reset); F(DrapeControl, pin_indices); F(DrapeControl, pin_count); F(DrapeControl, pin_targets);
    S(DrapeMeshCollider); F(DrapeMeshCollider, vertices); F(DrapeMeshCollider, vertex_count); F(DrapeMeshCollider, triangles);
    F(DrapeMeshCollider, triangle_count); F(DrapeMeshCollider, position); F(DrapeMeshCollider, rotation); F(DrapeMeshCollider, remove);
    S(DrapeSubmitExtras); F(DrapeSubmitExtras, thickness); F(DrapeSubmitExtras, contact_stiffness); F(DrapeSubmitExtras, scene);
    F(DrapeSubmitExtras, mesh_collider);
    S(DrapeRateCounters); F(DrapeRateCounters, step_downs); F(DrapeRateCounters, step_ups); F(DrapeRateCounters, rate);
    F(DrapeRateCounters, auto_);
    S(DrapeStateCounters); F(DrapeStateCounters, received); F(DrapeStateCounters, read); F(DrapeStateCounters, replaced);
    F(DrapeStateCounters, missed); F(DrapeStateCounters, unread); F(DrapeStateCounters, ticks); F(DrapeStateCounters, invalid);
    F(DrapeStateCounters, stale); F(DrapeStateCounters, last_tick);
    S(DrapeServerInfo); F(DrapeServerInfo, server); F(DrapeServerInfo, version_major); F(DrapeServerInfo, version_minor);
    F(DrapeServerInfo, tick_rate); F(DrapeServerInfo, tick); F(DrapeServerInfo, cloths); F(DrapeServerInfo, clients);
    F(DrapeServerInfo, vertices); F(DrapeServerInfo, solver); F(DrapeServerInfo, device); F(DrapeServerInfo, max_cloths);
    F(DrapeServerInfo, max_substeps); F(DrapeServerInfo, grace_period_s); F(DrapeServerInfo, stats_period_s);
    S(DrapeServerStats); F(DrapeServerStats, server); F(DrapeServerStats, tick); F(DrapeServerStats, time_ns); F(DrapeServerStats, uptime_s);
    F(DrapeServerStats, tick_rate); F(DrapeServerStats, cloths); F(DrapeServerStats, ticks); F(DrapeServerStats, missed_ticks);
    F(DrapeServerStats, bundles); F(DrapeServerStats, tick_mean_ms); F(DrapeServerStats, tick_max_ms); F(DrapeServerStats, quality_degraded);
    return 0;
}
