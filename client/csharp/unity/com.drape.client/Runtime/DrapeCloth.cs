// DrapeCloth.cs: a Unity component that submits a grid cloth to a Drape server and uploads its
// positions and normals into a Mesh every frame. Unity-only (UnityEngine); its engine-independent
// core (Drape.ClothStream, Drape.DrapeClient) is what client/csharp/tests runs under Mono. Not
// compiled or run here (no Unity on the build machines): see client/csharp/README.md.
#if UNITY_5_3_OR_NEWER
using System;
using Unity.Collections;
using Unity.Collections.LowLevel.Unsafe;
using UnityEngine;

namespace Drape.Unity
{
    /// One client per process, shared by every DrapeCloth (opened on first use, closed on quit).
    public static class DrapeConnection
    {
        static DrapeClient client;
        public static string Endpoint = "tcp/127.0.0.1:7447";

        public static DrapeClient Client
        {
            get
            {
                if (client == null)
                {
                    client = DrapeClient.Open(Endpoint, timeoutMs: 5000);
                    Application.quitting += () => { client.Dispose(); client = null; };
                }
                return client;
            }
        }
    }

    [RequireComponent(typeof(MeshFilter), typeof(MeshRenderer))]
    public sealed class DrapeCloth : MonoBehaviour
    {
        public int columns = 32, rows = 32;
        public float width = 0.6f, height = 0.9f;
        [Tooltip("Pinned vertices (row 0 is the top edge: 0 .. columns-1)")]
        public uint[] pinned = { 0, 31 };
        [Tooltip("Colliders the cloth wraps around (spheres / capsules from these transforms)")]
        public SphereCollider[] sphereColliders = new SphereCollider[0];
        public CapsuleCollider[] capsuleColliders = new CapsuleCollider[0];
        public Vector3 wind = Vector3.zero;
        public bool normals = true;
        [Tooltip("States kept unread between frames (a frame slower than a tick loses none)")]
        public uint queueSize = 8;
        [Tooltip("The pins follow this transform (e.g. the character's shoulders); null: this one. States arrive in world space, so keep this GameObject at the origin, unrotated")]
        public Transform anchor;

        Cloth cloth;
        ClothStream stream;
        Mesh mesh;
        NativeArray<Vector3> vertices, normalBuffer;
        float[] pinTargets;
        IntPtr[] one = new IntPtr[1];

        void Start()
        {
            var o = new ClothOptions
            {
                Pinned = pinned, Encoding = 2, Normals = normals, Bundle = true, QueueSize = queueSize, RetryMs = 30000,
                Features = Native.FEATURE_TETHERS | Native.FEATURE_COLLIDERS | (wind != Vector3.zero ? Native.FEATURE_WIND : 0),
                Wind = new double[] { wind.x, wind.y, wind.z }, Colliders = WorldColliders(),
            };
            Vector3 origin = Anchor.position;
            cloth = DrapeConnection.Client.SubmitGrid((uint)columns, (uint)rows, width, height, true, origin.x, origin.y, origin.z, o, async: true);
            stream = new ClothStream(cloth, normals);
            mesh = new Mesh { name = "drape " + name };
            mesh.MarkDynamic();
            vertices = new NativeArray<Vector3>(cloth.VertexCount, Allocator.Persistent);
            normalBuffer = new NativeArray<Vector3>(cloth.VertexCount, Allocator.Persistent);
            mesh.SetVertices(Reinterpret(stream.Positions, vertices));
            mesh.SetTriangles(stream.Triangles, 0);
            mesh.RecalculateNormals();
            GetComponent<MeshFilter>().sharedMesh = mesh;
            pinTargets = new float[3 * pinned.Length];
        }

        Collider[] WorldColliders()
        {
            var list = new Collider[sphereColliders.Length + capsuleColliders.Length];
            int i = 0;
            foreach (var s in sphereColliders)
            {
                Vector3 c = s.transform.TransformPoint(s.center);
                list[i++] = Collider.Sphere(c.x, c.y, c.z, s.radius * s.transform.lossyScale.x);
            }
            foreach (var c in capsuleColliders)
            {
                Vector3 axis = c.direction == 0 ? Vector3.right : c.direction == 1 ? Vector3.up : Vector3.forward;
                float half = Mathf.Max(0, c.height / 2 - c.radius);
                Vector3 a = c.transform.TransformPoint(c.center - axis * half), b = c.transform.TransformPoint(c.center + axis * half);
                list[i++] = Collider.Capsule(a.x, a.y, a.z, b.x, b.y, b.z, c.radius * c.transform.lossyScale.x);
            }
            return list;
        }

        Transform Anchor { get { return anchor != null ? anchor : transform; } }

        /// Pins follow the anchor (the cloth's top edge hangs from it). Not waited for.
        void MovePins()
        {
            if (cloth.Status != Native.CLOTH_LIVE) return;
            for (int i = 0; i < pinned.Length; i++)
            {
                int col = (int)pinned[i] % columns, row = (int)pinned[i] / columns;
                Vector3 p = Anchor.TransformPoint(new Vector3(width * col / (columns - 1), -height * row / (rows - 1), 0));
                pinTargets[3 * i] = p.x; pinTargets[3 * i + 1] = p.y; pinTargets[3 * i + 2] = p.z;
            }
            one[0] = cloth.Handle;
            DrapeConnection.Client.MovePinsMany(one, pinned, pinTargets);
        }

        void Update()
        {
            MovePins();
            if (stream.Update() == 0) return; // nothing new this frame
            // positions arrive in world space (this object stays at the origin, unrotated)
            mesh.SetVertices(Reinterpret(stream.Positions, vertices));
            if (normals) mesh.SetNormals(Reinterpret(stream.Normals, normalBuffer));
            mesh.RecalculateBounds();
        }

        static unsafe NativeArray<Vector3> Reinterpret(float[] src, NativeArray<Vector3> dst)
        {
            fixed (float* p = src)
                UnsafeUtility.MemCpy(dst.GetUnsafePtr(), p, src.Length * sizeof(float));
            return dst;
        }

        void OnDestroy()
        {
            if (cloth != null)
            {
                try { cloth.Remove(); } catch (DrapeException) { }
                cloth.Dispose();
            }
            if (vertices.IsCreated) vertices.Dispose();
            if (normalBuffer.IsCreated) normalBuffer.Dispose();
        }
    }
}
#endif
