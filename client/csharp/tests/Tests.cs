// Tests.cs: the C# binding's tests, run under Mono against a real `drape serve` (client/csharp/ci.sh).
// Usage: mono Tests.exe ENDPOINT LAYOUT_FILE CLOSED_ENDPOINT
//   ENDPOINT        a live server's Zenoh endpoint
//   LAYOUT_FILE     "name size" / "name.field offset" lines printed by layout.c (the C compiler's view)
//   CLOSED_ENDPOINT an endpoint where nothing listens
// Exits 0 when every test passed. Each assertion counts events; none depends on machine speed.
using System;
using System.Collections.Generic;
using System.IO;
using System.Runtime.InteropServices;
using Drape;

static unsafe class Tests
{
    static int failures;

    static void Check(bool ok, string what)
    {
        Console.WriteLine((ok ? "  ok   " : "  FAIL ") + what);
        if (!ok) failures++;
    }

    static void Run(string name, Action test)
    {
        Console.WriteLine("test " + name);
        try { test(); }
        catch (Exception e) { Check(false, name + " threw " + e); }
    }

    public static int Main(string[] args)
    {
        string endpoint = args[0], layout = args[1], closed = args[2];
        Console.WriteLine(DrapeClient.Version + " on " + Type.GetType("Mono.Runtime") + " " + Environment.Version);
        Run("layout", () => Layout(layout));
        Run("open_without_server", () => OpenWithoutServer(closed));
        Run("sixteen_capes_every_state_no_allocation", () => SixteenCapes(endpoint));
        Run("control_async_and_ids", () => ControlAsync(endpoint));
        Run("mesh_collider_and_rate", () => MeshColliderAndRate(endpoint));
        Console.WriteLine(failures == 0 ? "csharp: all tests passed" : "csharp: " + failures + " FAILED");
        return failures == 0 ? 0 : 1;
    }

    // Every struct's size and field offsets as Mono marshals them equal the C compiler's.
    static void Layout(string file)
    {
        var want = new Dictionary<string, long>();
        foreach (var line in File.ReadAllLines(file))
        {
            var p = line.Split(' ');
            want[p[0]] = long.Parse(p[1]);
        }
        Check(want.Count > 40, "layout file has " + want.Count + " entries");
        int compared = 0;
        foreach (var t in typeof(Native).GetNestedTypes())
        {
            if (!t.IsValueType) continue;
            long size;
            if (!want.TryGetValue(t.Name, out size)) { Check(false, t.Name + " is not in the layout file"); continue; }
            Check(Marshal.SizeOf(t) == size, t.Name + " size " + Marshal.SizeOf(t) + " == " + size);
            foreach (var f in t.GetFields())
            {
                if (f.IsStatic) continue;
                string key = t.Name + "." + FieldName(t.Name, f.Name);
                long off;
                if (!want.TryGetValue(key, out off)) continue; // split vector fields (origin_y...) checked by size
                Check((long)Marshal.OffsetOf(t, f.Name) == off, key + " at " + Marshal.OffsetOf(t, f.Name) + " == " + off);
                compared++;
            }
        }
        Check(compared > 40, compared + " field offsets compared");
    }

    // C# splits double[3] fields into x/y/z: the first one sits at the C array's offset.
    static string FieldName(string type, string f)
    {
        switch (f)
        {
            case "origin_x": return "origin";
            case "min_x": return "bounds_min";
            case "max_x": return "bounds_max";
            case "ax": return "a";
            case "bx": return "b";
            case "position_x": return "position";
            case "rotation_w": return "rotation";
            case "stiffness0": return "stiffness";
            case "compliance0": return "compliance";
            default: return f.EndsWith(">e__FixedBuffer") ? f : f;
        }
    }

    // Nothing listening: Open fails with E_UNAVAILABLE (it returned OK before) and its message
    // names no source file of the build machine.
    static void OpenWithoutServer(string closed)
    {
        try
        {
            DrapeClient.Open(closed, timeoutMs: 600).Dispose();
            Check(false, "Open succeeded with nothing listening at " + closed);
        }
        catch (DrapeException e)
        {
            Check(e.Code == Native.E_UNAVAILABLE, "code " + e.Code + " == E_UNAVAILABLE");
            Check(!e.Message.Contains(".rs:") && !e.Message.Contains("/src/"), "no source paths in: " + e.Message);
        }
        try
        {
            DrapeClient.Open("tcp/not an endpoint", timeoutMs: 600).Dispose();
            Check(false, "a bad endpoint was accepted");
        }
        catch (DrapeException e)
        {
            Check(!e.Message.Contains(".rs:") && !e.Message.Contains("/src/"), "bad endpoint: no source paths in: " + e.Message);
        }
    }

    const int N = 16, Cols = 32, Rows = 32, Frames = 240;

    // The C# engine loop: 16 bundled 32x32 capes submitted asynchronously with colliders, wind and
    // a material, pins moved every frame with MovePinsMany, every state read through ClothStream;
    // the steady frames allocate 0 bytes (the runtime's allocation counter), every cape's
    // counters add up, and no state was replaced unread.
    static void SixteenCapes(string endpoint)
    {
        using (var client = DrapeClient.Open(endpoint, timeoutMs: 120000)) // a cold server builds its kernels first
        {
            var info = client.ServerInfo();
            Check(info.tick_rate > 0 && info.version_major == 1, "server info: " + info.version_major + "." + info.version_minor + " at " + info.tick_rate + " Hz");
            uint[] pins = { 0, Cols / 3, 2 * Cols / 3, Cols - 1 };
            var mat = new Native.DrapeMaterial { fields = Native.MATERIAL_MASS | Native.MATERIAL_DAMPING, mass = 0.6, damping = 0.02 };
            var capes = new Cloth[N];
            var streams = new ClothStream[N];
            for (int i = 0; i < N; i++)
            {
                double x = 2.0 * i;
                var o = new ClothOptions
                {
                    Pinned = pins, Encoding = 2, Bundle = true, QueueSize = 64, RetryMs = 60000, Wind = new[] { 1.5, 0, 0.5 }, Material = mat,
                    Features = Native.FEATURE_TETHERS | Native.FEATURE_COLLIDERS | Native.FEATURE_WIND,
                    Colliders = new[] { Collider.Capsule(x, 0.6, 0, x, 1.4, 0, 0.22), Collider.Sphere(x, 1.65, 0, 0.12) },
                };
                capes[i] = client.SubmitGrid(Cols, Rows, 0.6, 0.9, true, x - 0.3, 1.5, -0.15, o, async: true);
                Check(capes[i].Status == Native.CLOTH_PENDING || capes[i].Status == Native.CLOTH_LIVE, "cape " + i + " returned at once");
            }
            int submitted = 0;
            Native.DrapeEvent ev;
            var deadline = DateTime.UtcNow.AddSeconds(90);
            while (submitted < N && DateTime.UtcNow < deadline)
            {
                if (!client.PollEvent(out ev, 200)) continue;
                if (ev.kind == Native.EVENT_SUBMITTED) submitted++;
                if (ev.kind == Native.EVENT_SUBMIT_FAILED) Check(false, "submit failed: " + Utf8Of(ev.message));
            }
            Check(submitted == N, submitted + " of " + N + " capes live");
            for (int i = 0; i < N; i++) streams[i] = new ClothStream(capes[i], false);
            var handles = new IntPtr[N];
            for (int i = 0; i < N; i++) handles[i] = capes[i].Handle;
            var targets = new float[3 * pins.Length * N];
            // the allocation counter must see an allocation (or the zero below proves nothing)
            long a0 = GC.GetAllocatedBytesForCurrentThread();
            var probe = new float[16];
            long a1 = GC.GetAllocatedBytesForCurrentThread();
            Check(a1 - a0 >= 64 && probe.Length == 16, "the allocation counter sees a 16-float array: " + (a1 - a0) + " bytes");

            // states that arrived while the others were being admitted: read, and counted apart
            var before0 = new Native.DrapeStateCounters[N];
            for (int i = 0; i < N; i++) { streams[i].Update(); before0[i] = capes[i].Counters; }
            long allocated = 0, states = 0, eventsSeen = 0, samples = 0;
            var drawn = new float[3 * Cols * Rows]; // cape 0 drawn at each frame's time (Sample)
            for (int frame = 0; frame < Frames; frame++)
            {
                long before = GC.GetAllocatedBytesForCurrentThread();
                double a = frame * (2 * Math.PI / 120);
                for (int i = 0; i < N; i++)
                    for (int p = 0; p < pins.Length; p++)
                    {
                        int k = 3 * (i * pins.Length + p);
                        targets[k] = (float)(2.0 * i - 0.3 + 0.6 * pins[p] / (Cols - 1) + 0.1 * Math.Cos(a));
                        targets[k + 1] = 1.5f;
                        targets[k + 2] = (float)(-0.15 + 0.1 * Math.Sin(a));
                    }
                client.MovePinsMany(handles, pins, targets);
                for (int i = 0; i < N; i++) states += streams[i].Update();
                if (capes[0].Sample(drawn)) samples++;
                while (client.PollEvent(out ev)) eventsSeen++;
                long after = GC.GetAllocatedBytesForCurrentThread();
                if (frame >= 10) allocated += after - before; // the first frames warm the JIT
                System.Threading.Thread.Sleep(16);
            }
            Check(allocated == 0, "frames 10.." + Frames + " allocated " + allocated + " bytes");
            Check(states > 0, states + " states read");
            Check(samples > Frames / 2 && capes[0].ClockOffsetNs.HasValue && !float.IsNaN(drawn[0]), "cape 0 sampled in " + samples + " frames");
            ulong read = 0, replaced = 0, missed = 0, unread = 0, ticks = 0;
            for (int i = 0; i < N; i++)
            {
                var k = capes[i].Counters;
                bool adds = k.read + k.replaced + k.missed + k.unread == k.ticks && k.received == k.read + k.replaced + k.unread;
                if (!adds) Check(false, "cape " + i + " counters: read " + k.read + " replaced " + k.replaced + " missed " + k.missed + " unread " + k.unread + " ticks " + k.ticks);
                Check((long)k.read == streams[i].StatesRead, "cape " + i + ": counters.read " + k.read + " == states read " + streams[i].StatesRead);
                read += k.read; replaced += k.replaced; missed += k.missed; unread += k.unread; ticks += k.ticks;
            }
            Console.WriteLine("  16 capes: read " + read + " replaced " + replaced + " missed " + missed + " unread " + unread + " ticks " + ticks);
            Check(read + replaced + missed + unread == ticks, "read + replaced + missed + unread == ticks");
            ulong replacedInLoop = 0;
            for (int i = 0; i < N; i++) replacedInLoop += capes[i].Counters.replaced - before0[i].replaced;
            Check(replacedInLoop == 0, "no state replaced unread during the frames (queue 64, read every frame): " + replacedInLoop
                  + " (" + replaced + " while waiting for the 16 submissions)");
            Native.DrapeServerStats st;
            Check(client.TryGetStats(out st) && st.ticks > 0, "stats received: " + st.ticks + " ticks, " + st.cloths + " cloths");
            foreach (var c in capes) { c.Remove(); c.Dispose(); }
        }
    }

    static string Utf8Of(byte* p) { return System.Text.Encoding.UTF8.GetString(p, Strlen(p)); }
    static int Strlen(byte* p) { int n = 0; while (p[n] != 0) n++; return n; }

    // ControlAsync returns at once with a request number; its REQUEST_DONE event carries it with
    // the resulting features; a refused one's REQUEST_FAILED names the cloth. An id buffer too
    // small is an error, not a silent truncation.
    static void ControlAsync(string endpoint)
    {
        using (var client = DrapeClient.Open(endpoint, timeoutMs: 30000))
        {
            var cloth = client.SubmitGrid(8, 8, 1, 1, true, 0, 2, 0, new ClothOptions { Pinned = new uint[] { 0, 7 } }, async: false);
            string id = cloth.Id;
            ulong req = cloth.ChangeFeaturesAsync(Native.FEATURE_WIND | Native.FEATURE_NORMALS, 0);
            ulong windReq = cloth.SetWindAsync(2, 0, 0);
            var bad = new Native.DrapeControl();
            uint* idx = stackalloc uint[1];
            float* tgt = stackalloc float[3];
            idx[0] = 3; // not a pinned vertex: refused by the server
            bad.pin_indices = idx; bad.pin_count = (UIntPtr)1; bad.pin_targets = tgt;
            ulong badReq = cloth.ControlAsync(ref bad);
            Check(req != 0 && windReq != 0 && badReq != 0 && req != windReq, "request numbers " + req + ", " + windReq + ", " + badReq);
            bool done = false, windDone = false, failed = false;
            Native.DrapeEvent ev;
            var deadline = DateTime.UtcNow.AddSeconds(30);
            while (!(done && windDone && failed) && DateTime.UtcNow < deadline)
            {
                if (!client.PollEvent(out ev, 200)) continue;
                if (ev.kind == Native.EVENT_REQUEST_DONE && ev.request == req)
                {
                    done = true;
                    Check((ev.features & (Native.FEATURE_WIND | Native.FEATURE_NORMALS)) == (Native.FEATURE_WIND | Native.FEATURE_NORMALS) && ev.tick > 0,
                          "features now 0x" + ev.features.ToString("x") + " from tick " + ev.tick);
                }
                if (ev.kind == Native.EVENT_REQUEST_DONE && ev.request == windReq) windDone = true;
                if (ev.kind == Native.EVENT_REQUEST_FAILED && ev.request == badReq)
                {
                    failed = true;
                    Check(Utf8Of(ev.cloth) == id, "the failure names the cloth: '" + Utf8Of(ev.cloth) + "' == '" + id + "'");
                }
            }
            Check(done && windDone && failed, "events: feature change done " + done + ", wind done " + windDone + ", refused move failed " + failed);
            byte* small = stackalloc byte[4];
            int rc = Native.drape_cloth_id(cloth.Handle, small, (UIntPtr)4);
            Check(rc == Native.E_INVALID_VALUE && small[0] == 0, "a 4-byte id buffer: code " + rc + ", empty string");
            cloth.Remove();
            cloth.Dispose();
        }
    }

    // Protocol 1.8 through the binding: a box set as a cloth's mesh collider (a bad one refused
    // with its triangle named, before sending), moved by a pose every frame without waiting, the
    // cloth kept out of it; removed; and the cloth's rate switched to every 2nd state.
    static void MeshColliderAndRate(string endpoint)
    {
        using (var client = DrapeClient.Open(endpoint, timeoutMs: 30000))
        {
            var info = client.ServerInfo();
            if (info.version_major == 1 && info.version_minor < 8) { Console.WriteLine("  skipped: server speaks 1." + info.version_minor); return; }
            const double half = 0.2;
            var box = new float[24];
            for (int i = 0; i < 8; i++)
                for (int k = 0; k < 3; k++) box[3 * i + k] = (float)((((i >> k) & 1) == 1 ? 1 : -1) * half);
            uint[] tris = { 0, 4, 6, 0, 6, 2, 1, 3, 7, 1, 7, 5, 0, 1, 5, 0, 5, 4, 2, 6, 7, 2, 7, 3, 0, 2, 3, 0, 3, 1, 4, 5, 7, 4, 7, 6 };
            var o = new ClothOptions { Substeps = 2, QueueSize = 64 };
            var cloth = client.SubmitGrid(9, 9, 0.6, 0.6, false, -0.3, 1.0 + half + 0.3, -0.3, o, async: false);
            var bad = (uint[])tris.Clone();
            bad[7] = bad[6];
            try
            {
                cloth.SetMeshCollider(box, bad, new[] { 0.0, 1.0, 0.0 });
                Check(false, "a degenerate triangle was accepted");
            }
            catch (DrapeException e)
            {
                Check(e.Code == Native.E_INVALID_VALUE && e.Message.Contains("triangle 2"), "bad mesh refused: " + e.Message);
            }
            ulong tick = cloth.SetMeshCollider(box, tris, new[] { 0.0, 1.0, 0.0 });
            var pos = new float[3 * cloth.VertexCount];
            int inside = 0, states = 0;
            var deadline = DateTime.UtcNow.AddSeconds(2);
            while (DateTime.UtcNow < deadline)
            {
                cloth.MoveMeshCollider(0, 1, 0); // the per-tick pose (here: still)
                Native.DrapeStateInfo si;
                if (!cloth.ReadState(pos, Span<float>.Empty, out si)) { System.Threading.Thread.Sleep(16); continue; }
                if (si.tick < tick + 1) continue;
                states++;
                for (int v = 0; v < cloth.VertexCount; v++)
                    if (Math.Abs(pos[3 * v]) < half - 1e-3 && Math.Abs(pos[3 * v + 1] - 1.0) < half - 1e-3 && Math.Abs(pos[3 * v + 2]) < half - 1e-3) inside++;
            }
            Check(states > 10 && inside == 0, states + " states, " + inside + " vertices inside the box mesh");
            cloth.RemoveMeshCollider();
            cloth.SetRate(Native.RATE_HALF);
            Check(cloth.RateCounters.rate == 2, "rate now every " + cloth.RateCounters.rate + " states");
            cloth.Remove();
            cloth.Dispose();
        }
    }
}
