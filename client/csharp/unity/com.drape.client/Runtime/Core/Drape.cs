// Drape.cs: a small managed layer over the drape C ABI (Native.cs). Load-time calls (Open,
// Submit*, ServerInfo) may allocate; the per-frame calls (PollEvent, ReadState, MovePinsMany,
// Counters, ControlAsync without colliders) allocate nothing: buffers are the caller's
// (Span<float> / arrays) and handles are IntPtrs. Engine independent: no UnityEngine here.
using System;
using System.Runtime.InteropServices;
using System.Text;

namespace Drape
{
    /// A drape error code with the library's message (DRAPE_E_*; see drape.h).
    public sealed class DrapeException : Exception
    {
        public readonly int Code;
        public DrapeException(int code, string message) : base(message) { Code = code; }

        internal static unsafe DrapeException Last(int code, string what)
        {
            byte* buf = stackalloc byte[512];
            Native.drape_last_error(buf, (UIntPtr)512);
            return new DrapeException(code, what + ": " + Utf8.Read(buf, 512));
        }

        internal static void Check(int rc, string what)
        {
            if (rc != Native.OK) throw Last(rc, what);
        }
    }

    internal static unsafe class Utf8
    {
        public static string Read(byte* p, int max)
        {
            int n = 0;
            while (n < max && p[n] != 0) n++;
            return Encoding.UTF8.GetString(p, n);
        }

        public static string Name(IntPtr p) { return Read((byte*)p, 64); }

        /// NUL-terminated UTF-8 in unmanaged memory (free with Marshal.FreeHGlobal); Zero for null.
        public static IntPtr Alloc(string s)
        {
            if (s == null) return IntPtr.Zero;
            byte[] b = Encoding.UTF8.GetBytes(s);
            IntPtr p = Marshal.AllocHGlobal(b.Length + 1);
            Marshal.Copy(b, 0, p, b.Length);
            Marshal.WriteByte(p, b.Length, 0);
            return p;
        }
    }

    public struct Collider
    {
        public int Kind;
        public double Ax, Ay, Az, Bx, By, Bz, Radius, Offset;

        public static Collider Sphere(double x, double y, double z, double r)
        { return new Collider { Kind = Native.COLLIDER_SPHERE, Ax = x, Ay = y, Az = z, Radius = r }; }

        public static Collider Capsule(double x0, double y0, double z0, double x1, double y1, double z1, double r)
        { return new Collider { Kind = Native.COLLIDER_CAPSULE, Ax = x0, Ay = y0, Az = z0, Bx = x1, By = y1, Bz = z1, Radius = r }; }

        /// The half space normal . x >= offset is outside.
        public static Collider Plane(double nx, double ny, double nz, double offset)
        { return new Collider { Kind = Native.COLLIDER_PLANE, Ax = nx, Ay = ny, Az = nz, Offset = offset }; }

        internal Native.DrapeCollider ToNative()
        {
            return new Native.DrapeCollider { kind = Kind, ax = Ax, ay = Ay, az = Az, bx = Bx, by = By, bz = Bz, radius = Radius, offset = Offset };
        }
    }

    /// Submission options (null / 0: the server's defaults).
    public sealed class ClothOptions
    {
        public uint[] Pinned;
        /// Native.ENCODING_*: 0 float32, 1 float16, 2 quant16, 3 predictive (protocol 1.5).
        public int Encoding;
        public bool Normals, Bundle;
        public string Quality;
        public double[] Gravity, Wind;
        /// Material fields to send (Native.MATERIAL_* bits in Fields).
        public Native.DrapeMaterial? Material;
        public Collider[] Colliders;
        /// Native.FEATURE_* mask (0: the server's default set).
        public uint Features, Iterations, Substeps;
        /// States kept unread (1: the newest only); read until ReadState returns false.
        public uint QueueSize = 1;
        /// Asynchronous submissions: how long refusals that may pass are retried (ms).
        public uint RetryMs;
    }

    /// A client: one Zenoh session to the Drape server(s). Dispose closes it.
    public sealed unsafe class DrapeClient : IDisposable
    {
        public IntPtr Handle { get; private set; }

        private DrapeClient(IntPtr h) { Handle = h; }

        public static string Version { get { return Utf8.Name(Native.drape_version()); } }

        /// Connect (comma-separated Zenoh endpoints). Unless lazy, waits up to the timeout for a
        /// server and throws DrapeException (E_UNAVAILABLE) when none is there.
        public static DrapeClient Open(string connect, string serverId = null, uint timeoutMs = 0, bool failover = true,
                                       bool lazy = false)
        {
            IntPtr c = Utf8.Alloc(connect), s = Utf8.Alloc(serverId);
            try
            {
                var o = new Native.DrapeClientOptions
                {
                    connect = c, server_id = s, timeout_ms = timeoutMs, no_failover = (byte)(failover ? 0 : 1), lazy = (byte)(lazy ? 1 : 0),
                };
                IntPtr h;
                DrapeException.Check(Native.drape_client_open(&o, out h), "drape_client_open");
                return new DrapeClient(h);
            }
            finally
            {
                if (c != IntPtr.Zero) Marshal.FreeHGlobal(c);
                if (s != IntPtr.Zero) Marshal.FreeHGlobal(s);
            }
        }

        public string Id
        {
            get
            {
                byte* buf = stackalloc byte[Native.ID_MAX];
                DrapeException.Check(Native.drape_client_id(Handle, buf, (UIntPtr)Native.ID_MAX), "drape_client_id");
                return Utf8.Read(buf, Native.ID_MAX);
            }
        }

        /// Asks the default server for its info (waits for the reply: at load time).
        public Native.DrapeServerInfo ServerInfo()
        {
            Native.DrapeServerInfo info;
            DrapeException.Check(Native.drape_client_server_info(Handle, IntPtr.Zero, &info), "drape_client_server_info");
            return info;
        }

        /// The default server's last stats publication; false before the first. Never blocks.
        public bool TryGetStats(out Native.DrapeServerStats stats)
        {
            Native.DrapeServerStats s;
            int rc = Native.drape_client_server_stats(Handle, IntPtr.Zero, &s);
            if (rc != Native.OK && rc != Native.NO_DATA) throw DrapeException.Last(rc, "drape_client_server_stats");
            stats = s;
            return rc == Native.OK;
        }

        /// The next event, if any (timeoutMs 0: never blocks). No allocation.
        public bool PollEvent(out Native.DrapeEvent ev, uint timeoutMs = 0)
        {
            Native.DrapeEvent e;
            int rc = Native.drape_client_poll_event(Handle, timeoutMs, &e);
            ev = e;
            return rc == Native.OK;
        }

        public Cloth SubmitGrid(uint cols, uint rows, double width, double height, bool vertical, double ox, double oy, double oz,
                                ClothOptions options, bool async)
        {
            var g = new Native.DrapeGrid { cols = cols, rows = rows, width = width, height = height, vertical = (byte)(vertical ? 1 : 0),
                                           origin_x = ox, origin_y = oy, origin_z = oz };
            using (var n = new NativeOptions(options))
            {
                Native.DrapeClothOptions o = n.Options;
                IntPtr h;
                int rc = async ? Native.drape_submit_grid_async(Handle, &g, &o, out h) : Native.drape_submit_grid(Handle, &g, &o, out h);
                DrapeException.Check(rc, async ? "drape_submit_grid_async" : "drape_submit_grid");
                return new Cloth(this, h);
            }
        }

        /// Submit a triangle mesh (3 floats per vertex, 3 indices per triangle).
        public Cloth SubmitMeshAsync(float[] vertices, int[] triangles, ClothOptions options)
        {
            using (var n = new NativeOptions(options))
            {
                Native.DrapeClothOptions o = n.Options;
                IntPtr h;
                fixed (float* v = vertices)
                fixed (int* t = triangles)
                    DrapeException.Check(Native.drape_submit_mesh_async(Handle, v, (UIntPtr)(vertices.Length / 3), (uint*)t,
                                                                        (UIntPtr)(triangles.Length / 3), &o, out h), "drape_submit_mesh_async");
                return new Cloth(this, h);
            }
        }

        /// The native options of a ClothOptions, its arrays pinned until Dispose.
        private sealed class NativeOptions : IDisposable
        {
            public Native.DrapeClothOptions Options;
            readonly GCHandle[] pins = new GCHandle[4];
            readonly IntPtr quality, material;

            IntPtr Pin(int i, object array)
            {
                if (array == null) return IntPtr.Zero;
                pins[i] = GCHandle.Alloc(array, GCHandleType.Pinned);
                return pins[i].AddrOfPinnedObject();
            }

            public NativeOptions(ClothOptions o)
            {
                o = o ?? new ClothOptions();
                var cols = o.Colliders ?? new Collider[0];
                var nc = new Native.DrapeCollider[cols.Length];
                for (int i = 0; i < cols.Length; i++) nc[i] = cols[i].ToNative();
                var pinned = o.Pinned ?? new uint[0];
                quality = Utf8.Alloc(o.Quality);
                if (o.Material.HasValue)
                {
                    material = Marshal.AllocHGlobal(sizeof(Native.DrapeMaterial));
                    *(Native.DrapeMaterial*)material = o.Material.Value;
                }
                Options = new Native.DrapeClothOptions
                {
                    pinned = (uint*)Pin(0, pinned), pinned_count = (UIntPtr)pinned.Length, encoding = o.Encoding,
                    normals = (byte)(o.Normals ? 1 : 0), bundle = (byte)(o.Bundle ? 1 : 0), quality = quality,
                    gravity = (double*)Pin(1, o.Gravity), wind = (double*)Pin(2, o.Wind), material = (Native.DrapeMaterial*)material,
                    colliders = (Native.DrapeCollider*)Pin(3, nc), collider_count = (UIntPtr)nc.Length, features = o.Features,
                    iterations = o.Iterations, substeps = o.Substeps, queue_size = o.QueueSize, retry_ms = o.RetryMs,
                };
            }

            public void Dispose()
            {
                foreach (var p in pins) if (p.IsAllocated) p.Free();
                if (quality != IntPtr.Zero) Marshal.FreeHGlobal(quality);
                if (material != IntPtr.Zero) Marshal.FreeHGlobal(material);
            }
        }

        /// Move pins `indices` of every cloth in `cloths` (IntPtr handles, Cloth.Handle) to
        /// `targets` (3 floats per index, cloth by cloth), not waited for. No allocation.
        public void MovePinsMany(ReadOnlySpan<IntPtr> cloths, ReadOnlySpan<uint> indices, ReadOnlySpan<float> targets)
        {
            if (targets.Length < 3 * cloths.Length * indices.Length) throw new ArgumentException("targets too short");
            fixed (IntPtr* c = cloths)
            fixed (uint* i = indices)
            fixed (float* t = targets)
            {
                int rc = Native.drape_move_pins_many(Handle, c, (UIntPtr)cloths.Length, i, (UIntPtr)indices.Length, t, 0, null, null);
                if (rc != Native.OK) throw DrapeException.Last(rc, "drape_move_pins_many");
            }
        }

        public void Dispose()
        {
            if (Handle != IntPtr.Zero) Native.drape_client_close(Handle, 1);
            Handle = IntPtr.Zero;
        }
    }

    /// A submitted cloth. Dispose frees the handle (it does not remove the cloth: Remove does).
    public sealed unsafe class Cloth : IDisposable
    {
        public IntPtr Handle { get; private set; }
        public readonly DrapeClient Client;
        public readonly int VertexCount;
        public readonly ulong Number;

        internal Cloth(DrapeClient client, IntPtr h)
        {
            Client = client;
            Handle = h;
            VertexCount = (int)Native.drape_cloth_vertex_count(h);
            Number = Native.drape_cloth_handle(h);
        }

        public int TriangleCount { get { return (int)Native.drape_cloth_triangle_count(Handle); } }
        /// Native.CLOTH_*.
        public int Status { get { return Native.drape_cloth_status(Handle); } }

        public string Id
        {
            get
            {
                byte* buf = stackalloc byte[Native.ID_MAX];
                DrapeException.Check(Native.drape_cloth_id(Handle, buf, (UIntPtr)Native.ID_MAX), "drape_cloth_id");
                return Utf8.Read(buf, Native.ID_MAX);
            }
        }

        public void RestMesh(Span<float> positions, Span<int> triangles)
        {
            fixed (float* p = positions)
            fixed (int* t = triangles)
                DrapeException.Check(Native.drape_cloth_rest_mesh(Handle, p, (UIntPtr)positions.Length, (uint*)t, (UIntPtr)triangles.Length),
                                     "drape_cloth_rest_mesh");
        }

        /// Decode the next unread state into `positions` (3 floats per vertex; `normals` may be
        /// empty): true, or false when none is new. Never blocks; no allocation.
        public bool ReadState(Span<float> positions, Span<float> normals, out Native.DrapeStateInfo info)
        {
            return Read(positions, normals, out info, false);
        }

        /// The newest state, read before or not (older unread ones dropped): false before the first.
        public bool ReadLatest(Span<float> positions, Span<float> normals, out Native.DrapeStateInfo info)
        {
            return Read(positions, normals, out info, true);
        }

        private bool Read(Span<float> positions, Span<float> normals, out Native.DrapeStateInfo info, bool latest)
        {
            Native.DrapeStateInfo i;
            int rc;
            fixed (float* p = positions)
            fixed (float* n = normals)
            {
                rc = latest
                    ? Native.drape_cloth_read_latest(Handle, p, (UIntPtr)positions.Length, normals.Length > 0 ? n : null, (UIntPtr)normals.Length, &i)
                    : Native.drape_cloth_read_state(Handle, p, (UIntPtr)positions.Length, normals.Length > 0 ? n : null, (UIntPtr)normals.Length, &i);
            }
            info = i;
            if (rc == Native.OK) return true;
            if (rc == Native.NO_DATA) return false;
            throw DrapeException.Last(rc, "drape_cloth_read_state");
        }

        /// The positions to draw now (`nowNs` 0; else a render time on this client's clock, Unix
        /// ns) into `positions` (3 floats per vertex): the last two states interpolated `delayNs`
        /// behind the newest (negative: one tick), so that a renderer faster than the server moves
        /// the cloth every frame at the cost of that delay; `extrapolate`: carried past the newest
        /// state instead (no delay, overshoots where the motion turns). False before the first
        /// state. Takes nothing from the state queue. Never blocks; no allocation.
        public bool Sample(Span<float> positions, bool extrapolate = false, long delayNs = -1, ulong nowNs = 0)
        {
            int rc;
            fixed (float* p = positions)
                rc = Native.drape_cloth_sample(Handle, nowNs, delayNs, extrapolate ? (byte)1 : (byte)0, p, (UIntPtr)positions.Length);
            if (rc == Native.OK) return true;
            if (rc == Native.NO_DATA) return false;
            throw DrapeException.Last(rc, "drape_cloth_sample");
        }

        /// This client's clock minus the server's as the cloth's states measure it (ns), or null
        /// before the first state: what `Sample` maps render times by.
        public long? ClockOffsetNs
        {
            get
            {
                long o;
                int rc = Native.drape_cloth_clock_offset(Handle, &o);
                if (rc == Native.OK) return o;
                if (rc == Native.NO_DATA) return null;
                throw DrapeException.Last(rc, "drape_cloth_clock_offset");
            }
        }

        public Native.DrapeStateCounters Counters
        {
            get
            {
                Native.DrapeStateCounters k;
                DrapeException.Check(Native.drape_cloth_counters(Handle, &k), "drape_cloth_counters");
                return k;
            }
        }

        /// Send a control without waiting; its outcome is an event (REQUEST_DONE / REQUEST_FAILED)
        /// carrying the returned number. Fill `control` with pointers you keep fixed for the call.
        public ulong ControlAsync(ref Native.DrapeControl control)
        {
            ulong request;
            fixed (Native.DrapeControl* c = &control)
                DrapeException.Check(Native.drape_cloth_control_async(Handle, c, &request), "drape_cloth_control_async");
            return request;
        }

        /// Switch features on and off (Native.FEATURE_* masks) without waiting.
        public ulong ChangeFeaturesAsync(uint add, uint remove)
        {
            var c = new Native.DrapeControl { features_add = add, features_remove = remove };
            return ControlAsync(ref c);
        }

        /// Set the wind without waiting.
        public ulong SetWindAsync(double x, double y, double z)
        {
            double* w = stackalloc double[3];
            w[0] = x; w[1] = y; w[2] = z;
            var c = new Native.DrapeControl { wind = w };
            return ControlAsync(ref c);
        }

        /// Replace the colliders without waiting (e.g. the character's body moved).
        public ulong SetCollidersAsync(ReadOnlySpan<Collider> colliders)
        {
            Native.DrapeCollider* n = stackalloc Native.DrapeCollider[Math.Max(colliders.Length, 1)];
            for (int i = 0; i < colliders.Length; i++) n[i] = colliders[i].ToNative();
            var c = new Native.DrapeControl { colliders = n, collider_count = (UIntPtr)colliders.Length, set_colliders = 1 };
            return ControlAsync(ref c);
        }

        /// Protocol 1.8: set the cloth's own mesh collider (a new mesh: 3 floats per vertex in its own
        /// frame, 3 indices per triangle, counter-clockwise seen from outside), or re-pose it
        /// (`triangles` null: new positions of its vertices), at the pose (position; rotation w, x, y,
        /// z, null: the identity). Waits for the reply: the first tick showing it. A bad mesh throws
        /// with the offending triangle or value named, before anything is sent.
        public ulong SetMeshCollider(float[] vertices, uint[] triangles, double[] position, double[] rotation = null)
        {
            ulong tick;
            fixed (float* v = vertices)
            fixed (uint* t = triangles)
            {
                var m = MeshOf(position, rotation);
                m.vertices = v; m.vertex_count = (UIntPtr)(vertices.Length / 3);
                m.triangles = t; m.triangle_count = (UIntPtr)(triangles == null ? 0 : triangles.Length / 3);
                DrapeException.Check(Native.drape_cloth_set_mesh_collider(Handle, &m, 1, &tick), "drape_cloth_set_mesh_collider");
            }
            return tick;
        }

        /// Protocol 1.8: the per-tick rigid move of the cloth's mesh collider, without waiting (a
        /// failure is a REQUEST_FAILED event). Allocates nothing.
        public void MoveMeshCollider(double x, double y, double z, double qw = 1, double qx = 0, double qy = 0, double qz = 0)
        {
            double* p = stackalloc double[3];
            double* q = stackalloc double[4];
            p[0] = x; p[1] = y; p[2] = z;
            q[0] = qw; q[1] = qx; q[2] = qy; q[3] = qz;
            DrapeException.Check(Native.drape_cloth_move_mesh_collider(Handle, p, q, 0, null), "drape_cloth_move_mesh_collider");
        }

        /// Protocol 1.8: remove the cloth's mesh collider (waits for the reply).
        public void RemoveMeshCollider()
        {
            var m = new Native.DrapeMeshCollider { remove = 1 };
            DrapeException.Check(Native.drape_cloth_set_mesh_collider(Handle, &m, 1, null), "drape_cloth_set_mesh_collider");
        }

        internal static Native.DrapeMeshCollider MeshOf(double[] position, double[] rotation)
        {
            var m = new Native.DrapeMeshCollider();
            if (position != null) { m.position_x = position[0]; m.position_y = position[1]; m.position_z = position[2]; }
            if (rotation != null) { m.rotation_w = rotation[0]; m.rotation_x = rotation[1]; m.rotation_y = rotation[2]; m.rotation_z = rotation[3]; }
            return m;
        }

        /// Protocol 1.8: take every `rate`-th state of this cloth (Native.RATE_FULL, _HALF, _THIRD; 1.9: _SIXTH, _TWELFTH).
        public void SetRate(uint rate)
        {
            DrapeException.Check(Native.drape_cloth_set_rate(Handle, rate), "drape_cloth_set_rate");
        }

        /// Protocol 1.8: the cloth's rate and its governor's steps.
        public Native.DrapeRateCounters RateCounters
        {
            get
            {
                Native.DrapeRateCounters k;
                DrapeException.Check(Native.drape_cloth_rate_counters(Handle, &k), "drape_cloth_rate_counters");
                return k;
            }
        }

        /// Remove the cloth from its server (waits for the reply). Returns its last tick.
        public ulong Remove()
        {
            ulong last;
            DrapeException.Check(Native.drape_cloth_remove(Handle, &last), "drape_cloth_remove");
            return last;
        }

        public void Dispose()
        {
            if (Handle != IntPtr.Zero) Native.drape_cloth_free(Handle);
            Handle = IntPtr.Zero;
        }
    }

    /// The engine-independent core of a rendered cloth: the buffers a mesh is uploaded from and
    /// the per-frame read of every state that arrived (what DrapeCloth runs each frame). No
    /// allocation per frame.
    public sealed class ClothStream
    {
        public readonly Cloth Cloth;
        /// 3 floats per vertex, xyz interleaved: the newest state read.
        public readonly float[] Positions, Normals;
        public readonly int[] Triangles;
        public Native.DrapeStateInfo Info;
        /// States read by Update, in all.
        public long StatesRead;

        public ClothStream(Cloth cloth, bool normals)
        {
            Cloth = cloth;
            Positions = new float[3 * cloth.VertexCount];
            Normals = normals ? new float[3 * cloth.VertexCount] : new float[0];
            Triangles = new int[3 * cloth.TriangleCount];
            cloth.RestMesh(Positions, Triangles);
        }

        /// Read every state that arrived since the last call (the buffers end with the newest):
        /// how many were read (0: nothing new; the buffers keep the last state).
        public int Update()
        {
            if (Cloth.Status == Native.CLOTH_PENDING) return 0;
            int n = 0;
            Native.DrapeStateInfo info;
            while (Cloth.ReadState(Positions, Normals, out info))
            {
                Info = info;
                n++;
            }
            StatesRead += n;
            return n;
        }
    }
}
