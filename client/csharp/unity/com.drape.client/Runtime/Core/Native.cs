// Native.cs: P/Invoke declarations of the drape C ABI (client/rust/include/drape.h). Every
// struct is blittable (bools are bytes, strings are fixed byte buffers) so that calls marshal
// nothing and allocate nothing; tests/LayoutTest checks each size and offset against the C
// compiler's. Engine independent: no UnityEngine here.
using System;
using System.Runtime.InteropServices;

namespace Drape
{
    public static unsafe class Native
    {
        public const string Lib = "drape";

        public const int OK = 0, NO_DATA = 100;
        public const int E_INVALID_VALUE = 5, E_NOT_FOUND = 9, E_UNAVAILABLE = 13, E_SERVER_LOST = 14, E_CLOSED = 15,
                         E_OVERLOADED = 17;
        public const uint FEATURE_XPBD = 1, FEATURE_TETHERS = 2, FEATURE_COLLIDERS = 4, FEATURE_WIND = 8, FEATURE_NORMALS = 16;
        public const uint FEATURES_UNKNOWN = 0xFFFFFFFF;
        public const int EVENT_SERVER_FOUND = 1, EVENT_SERVER_LOST = 2, EVENT_CLOTH_LOST = 3, EVENT_CLOTH_RESUBMITTED = 4,
                         EVENT_REQUEST_FAILED = 5, EVENT_REQUEST_DONE = 6, EVENT_SUBMITTED = 7, EVENT_SUBMIT_FAILED = 8;
        public const int CLOTH_PENDING = 0, CLOTH_LIVE = 1, CLOTH_RESUBMITTING = 2, CLOTH_LOST = 3, CLOTH_REMOVED = 4;
        public const int COLLIDER_SPHERE = 0, COLLIDER_CAPSULE = 1, COLLIDER_PLANE = 2;
        /// State encodings (ClothOptions.Encoding); 3, predictive, needs a protocol 1.5 server (decoded by
        /// the library on delivery, read as float32; its step: drape_client_set_predictive_step).
        public const int ENCODING_FLOAT32 = 0, ENCODING_FLOAT16 = 1, ENCODING_QUANT16 = 2, ENCODING_PREDICTIVE = 3;
        /// Rates per subscriber (protocol 1.8; drape_client_set_rate, drape_cloth_set_rate,
        /// drape_client_set_bundle_rate): every state, every 2nd, every 3rd, (1.9) every 6th, every 12th,
        /// or AUTO (client-wide: full rate, stepped down while states arrive late). A cloth on a server
        /// older than 1.8 takes every state; on a 1.8 server every 3rd at most.
        public const uint RATE_AUTO = 0, RATE_FULL = 1, RATE_HALF = 2, RATE_THIRD = 3, RATE_SIXTH = 6, RATE_TWELFTH = 12;
        public const uint MATERIAL_MASS = 1, MATERIAL_STIFFNESS = 2, MATERIAL_COMPLIANCE = 4, MATERIAL_DAMPING = 8,
                          MATERIAL_FRICTION = 16, MATERIAL_DRAG = 32, MATERIAL_LIFT = 64, MATERIAL_AIR_DENSITY = 128,
                          MATERIAL_TETHER_LIMIT = 256;
        public const int ID_MAX = 72;

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeClientOptions
        {
            public IntPtr connect, server_id, client_id, namespace_;
            public uint timeout_ms;
            public byte no_failover, lazy;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeEvent
        {
            public int kind, code;
            public ulong handle;
            public fixed byte server[72];
            public fixed byte cloth[72];
            public fixed byte old_cloth[72];
            public fixed byte message[256];
            public fixed byte old_server[72];
            public ulong resumed_tick;
            public int reason;
            public byte resumed, kept;
            public ulong request, tick;
            public uint features;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeGrid
        {
            public uint cols, rows;
            public double width, height;
            public byte vertical;
            public double origin_x, origin_y, origin_z;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeClothOptions
        {
            public uint* pinned;
            public UIntPtr pinned_count;
            public int encoding;
            public byte normals, bundle;
            public IntPtr quality;
            public double* gravity;
            public double* wind;
            public DrapeMaterial* material;
            public DrapeCollider* colliders;
            public UIntPtr collider_count;
            public uint features, iterations, substeps, queue_size, retry_ms;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeStateInfo
        {
            public ulong tick, server_time_ns, receive_time_ns;
            public uint vertex_count;
            public ushort flags;
            public byte encoding, has_normals, reset;
            public float min_x, min_y, min_z, max_x, max_y, max_z;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeCollider
        {
            public int kind;
            public double ax, ay, az, bx, by, bz;
            public double radius, offset;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeMaterial
        {
            public uint fields;
            public double mass;
            public double stiffness0, stiffness1, stiffness2;
            public double compliance0, compliance1, compliance2;
            public double damping, friction, drag, lift, air_density, tether_limit;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeControl
        {
            public double* gravity;
            public double* wind;
            public DrapeMaterial* material;
            public DrapeCollider* colliders;
            public UIntPtr collider_count;
            public byte set_colliders;
            public uint features_add, features_remove, iterations, substeps;
            public IntPtr quality;
            public byte set_state;
            public int encoding;
            public byte normals, reset;
            public uint* pin_indices;
            public UIntPtr pin_count;
            public float* pin_targets;
        }

        /// Protocol 1.8: a mesh collider change (drape.h's DrapeMeshCollider): vertices and triangles
        /// a new mesh, vertices alone a re-pose, neither a rigid move to the pose, remove the removal.
        /// rotation is w, x, y, z (all 0: the identity).
        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeMeshCollider
        {
            public float* vertices;
            public UIntPtr vertex_count;
            public uint* triangles;
            public UIntPtr triangle_count;
            public double position_x, position_y, position_z;
            public double rotation_w, rotation_x, rotation_y, rotation_z;
            public byte remove;
        }

        /// drape_submit_grid_ex's fields beyond DrapeClothOptions (0 / null: not sent): 1.6 thickness and
        /// contact stiffness, 1.7 scene (a UTF-8 id), 1.8 the cloth's own mesh collider.
        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeSubmitExtras
        {
            public double thickness, contact_stiffness;
            public IntPtr scene;
            public DrapeMeshCollider* mesh_collider;
        }

        /// Protocol 1.8: a subscription's rate and what RATE_AUTO did to it.
        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeRateCounters
        {
            public ulong step_downs, step_ups;
            public uint rate;
            public byte auto_;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeStateCounters
        {
            public ulong received, read, replaced, missed, unread, ticks, invalid, stale, last_tick;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeServerInfo
        {
            public fixed byte server[72];
            public uint version_major, version_minor;
            public double tick_rate;
            public ulong tick, cloths, clients, vertices;
            public fixed byte solver[32];
            public fixed byte device[128];
            public ulong max_cloths, max_cloths_per_client, max_vertices_per_cloth, max_total_vertices, max_message_bytes,
                         max_pin_updates, max_batch_items, max_colliders, max_iterations, max_substeps;
            public double grace_period_s, stats_period_s;
        }

        [StructLayout(LayoutKind.Sequential)]
        public struct DrapeServerStats
        {
            public fixed byte server[72];
            public ulong tick, time_ns;
            public double uptime_s, tick_rate;
            public ulong cloths, clients, alive_clients, vertices, ticks, missed_ticks, skipped_frames, published, unwatched,
                         publish_errors, overload_refusals, nan_resets, reclaimed, controls_applied, controls_coalesced, bundles;
            public double tick_mean_ms, tick_max_ms;
            public ulong quality_degraded;
        }

        [DllImport(Lib)] public static extern IntPtr drape_version();
        [DllImport(Lib)] public static extern int drape_last_error(byte* buf, UIntPtr len);
        [DllImport(Lib)] public static extern IntPtr drape_error_name(int code);
        [DllImport(Lib)] public static extern int drape_client_open(DrapeClientOptions* options, out IntPtr client);
        [DllImport(Lib)] public static extern void drape_client_close(IntPtr client, byte remove);
        [DllImport(Lib)] public static extern int drape_client_id(IntPtr client, byte* buf, UIntPtr len);
        [DllImport(Lib)] public static extern int drape_client_poll_event(IntPtr client, uint timeout_ms, DrapeEvent* ev);
        [DllImport(Lib)] public static extern int drape_client_server_info(IntPtr client, IntPtr server, DrapeServerInfo* info);
        [DllImport(Lib)] public static extern int drape_client_server_stats(IntPtr client, IntPtr server, DrapeServerStats* stats);
        [DllImport(Lib)] public static extern int drape_submit_grid(IntPtr client, DrapeGrid* grid, DrapeClothOptions* options, out IntPtr cloth);
        [DllImport(Lib)] public static extern int drape_submit_grid_async(IntPtr client, DrapeGrid* grid, DrapeClothOptions* options, out IntPtr cloth);
        [DllImport(Lib)] public static extern int drape_submit_mesh_async(IntPtr client, float* vertices, UIntPtr vertex_count,
                                                                         uint* triangles, UIntPtr triangle_count,
                                                                         DrapeClothOptions* options, out IntPtr cloth);
        [DllImport(Lib)] public static extern void drape_cloth_free(IntPtr cloth);
        [DllImport(Lib)] public static extern uint drape_cloth_vertex_count(IntPtr cloth);
        [DllImport(Lib)] public static extern uint drape_cloth_triangle_count(IntPtr cloth);
        [DllImport(Lib)] public static extern ulong drape_cloth_handle(IntPtr cloth);
        [DllImport(Lib)] public static extern int drape_cloth_id(IntPtr cloth, byte* buf, UIntPtr len);
        [DllImport(Lib)] public static extern int drape_cloth_status(IntPtr cloth);
        [DllImport(Lib)] public static extern int drape_cloth_rest_mesh(IntPtr cloth, float* positions, UIntPtr positions_len,
                                                                       uint* triangles, UIntPtr triangles_len);
        [DllImport(Lib)] public static extern int drape_cloth_read_state(IntPtr cloth, float* positions, UIntPtr positions_len,
                                                                        float* normals, UIntPtr normals_len, DrapeStateInfo* info);
        [DllImport(Lib)] public static extern int drape_cloth_read_latest(IntPtr cloth, float* positions, UIntPtr positions_len,
                                                                         float* normals, UIntPtr normals_len, DrapeStateInfo* info);
        [DllImport(Lib)] public static extern int drape_cloth_sample(IntPtr cloth, ulong now_ns, long delay_ns, byte extrapolate,
                                                                    float* positions, UIntPtr positions_len);
        [DllImport(Lib)] public static extern int drape_cloth_clock_offset(IntPtr cloth, long* offset_ns);
        [DllImport(Lib)] public static extern int drape_cloth_counters(IntPtr cloth, DrapeStateCounters* counters);
        [DllImport(Lib)] public static extern int drape_cloth_control(IntPtr cloth, DrapeControl* control, ulong* tick, uint* features);
        [DllImport(Lib)] public static extern int drape_cloth_control_async(IntPtr cloth, DrapeControl* control, ulong* request);
        [DllImport(Lib)] public static extern int drape_cloth_remove(IntPtr cloth, ulong* last_tick);
        // protocol 1.8: rates per subscriber (RATE_*)
        [DllImport(Lib)] public static extern int drape_client_set_rate(IntPtr client, uint rate);
        [DllImport(Lib)] public static extern int drape_client_set_bundle_rate(IntPtr client, uint rate);
        [DllImport(Lib)] public static extern int drape_cloth_set_rate(IntPtr cloth, uint rate);
        [DllImport(Lib)] public static extern int drape_cloth_rate_counters(IntPtr cloth, DrapeRateCounters* counters);
        [DllImport(Lib)] public static extern int drape_client_bundle_rate_counters(IntPtr client, DrapeRateCounters* counters);
        // protocol 1.8: mesh colliders (a cloth's own, a scene's from its owner)
        [DllImport(Lib)] public static extern int drape_submit_grid_ex(IntPtr client, DrapeGrid* grid, DrapeClothOptions* options,
                                                                      DrapeSubmitExtras* extras, out IntPtr cloth);
        [DllImport(Lib)] public static extern int drape_cloth_set_mesh_collider(IntPtr cloth, DrapeMeshCollider* mesh, byte wait, ulong* tick);
        [DllImport(Lib)] public static extern int drape_cloth_move_mesh_collider(IntPtr cloth, double* position, double* rotation, byte wait,
                                                                                ulong* tick);
        [DllImport(Lib)] public static extern int drape_batch_set_mesh_collider(IntPtr batch, IntPtr cloth, DrapeMeshCollider* mesh);
        [DllImport(Lib)] public static extern int drape_client_set_scene_mesh_collider(IntPtr client, IntPtr scene, DrapeMeshCollider* mesh,
                                                                                      IntPtr server, ulong* tick);
        [DllImport(Lib)] public static extern int drape_move_pins_many(IntPtr client, IntPtr* cloths, UIntPtr cloth_count,
                                                                      uint* indices, UIntPtr index_count, float* targets,
                                                                      byte wait, int* codes, ulong* ticks);
    }
}
