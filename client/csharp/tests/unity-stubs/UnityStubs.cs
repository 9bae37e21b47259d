// UnityStubs.cs: the few UnityEngine / Unity.Collections declarations Runtime/DrapeCloth.cs uses,
// with the signatures of Unity 2021.3's API and no behaviour, so that ci.sh can compile the
// component with mcs (a type or signature error fails CI). This is not Unity: nothing here runs.
using System;

namespace UnityEngine
{
    public class Object { public string name; }
    public class Component : Object
    {
        public Transform transform;
        public T GetComponent<T>() { return default(T); }
    }
    public class Behaviour : Component { }
    public class MonoBehaviour : Behaviour { }
    public class Transform : Component
    {
        public Vector3 position, lossyScale;
        public Vector3 TransformPoint(Vector3 p) { return p; }
    }
    public class Collider : Component { }
    public class SphereCollider : Collider { public Vector3 center; public float radius; }
    public class CapsuleCollider : Collider { public Vector3 center; public float radius, height; public int direction; }
    public class MeshFilter : Component { public Mesh sharedMesh; }
    public class MeshRenderer : Component { }
    public sealed class Mesh : Object
    {
        public void MarkDynamic() { }
        public void SetVertices<T>(Unity.Collections.NativeArray<T> v) where T : struct { }
        public void SetNormals<T>(Unity.Collections.NativeArray<T> v) where T : struct { }
        public void SetTriangles(int[] triangles, int submesh) { }
        public void RecalculateNormals() { }
        public void RecalculateBounds() { }
    }
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static Vector3 zero { get { return new Vector3(); } }
        public static Vector3 right { get { return new Vector3(1, 0, 0); } }
        public static Vector3 up { get { return new Vector3(0, 1, 0); } }
        public static Vector3 forward { get { return new Vector3(0, 0, 1); } }
        public static Vector3 operator *(Vector3 a, float d) { return new Vector3(a.x * d, a.y * d, a.z * d); }
        public static Vector3 operator +(Vector3 a, Vector3 b) { return new Vector3(a.x + b.x, a.y + b.y, a.z + b.z); }
        public static Vector3 operator -(Vector3 a, Vector3 b) { return new Vector3(a.x - b.x, a.y - b.y, a.z - b.z); }
        public static bool operator ==(Vector3 a, Vector3 b) { return a.x == b.x && a.y == b.y && a.z == b.z; }
        public static bool operator !=(Vector3 a, Vector3 b) { return !(a == b); }
        public override bool Equals(object o) { return o is Vector3 && (Vector3)o == this; }
        public override int GetHashCode() { return 0; }
    }
    public static class Mathf { public static float Max(float a, float b) { return a > b ? a : b; } }
    public static class Application { public static event Action quitting { add { } remove { } } }
    [AttributeUsage(AttributeTargets.Class)]
    public sealed class RequireComponentAttribute : Attribute { public RequireComponentAttribute(Type a, Type b) { } }
    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string t) { } }
}

namespace Unity.Collections
{
    public enum Allocator { Persistent = 4 }
    public struct NativeArray<T> : IDisposable where T : struct
    {
        public NativeArray(int length, Allocator allocator) { IsCreated = true; }
        public bool IsCreated { get; private set; }
        public void Dispose() { }
    }
}

namespace Unity.Collections.LowLevel.Unsafe
{
    public static unsafe class UnsafeUtility { public static void MemCpy(void* dst, void* src, long size) { } }
    public static unsafe class NativeArrayUnsafeUtility
    {
        public static void* GetUnsafePtr<T>(this NativeArray<T> a) where T : struct { return null; }
    }
}
