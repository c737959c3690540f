#version 450
// anchordp3's one-pass camera shader, fragment stage: Lambertian surfaces under the scene's
// ambient, directional and point lights (no shadows, no specular, no image-based light), gamma 2.2.
// Writes one packed buffer that the camera reads back in one copy: per pixel, the colour as four
// bytes (r, g, b, a), the depth along the optical axis as float bits (metres; 0 where nothing was
// hit: the buffer is cleared to zero), and the entity and mesh segmentation ids.

layout (constant_id = 0) const int NUM_DIRECTIONAL_LIGHTS = 0;
layout (constant_id = 1) const int NUM_POINT_LIGHTS = 0;

layout(set = 0, binding = 0) uniform CameraBuffer {
  mat4 viewMatrix;
  mat4 projectionMatrix;
  mat4 viewMatrixInverse;
  mat4 projectionMatrixInverse;
  float width;
  float height;
} camera;

layout(set = 1, binding = 0) uniform ObjectTransformBuffer {
  mat4 modelMatrix;
} object;

layout(set = 1, binding = 1) uniform ObjectDataBuffer {
  uvec4 segmentation;
  float transparency;
  int shadeFlat;
} objectData;

layout(set = 2, binding = 0) uniform MaterialBuffer {
  vec4 emission;
  vec4 baseColor;
  float fresnel;
  float roughness;
  float metallic;
  float transmission;
  float ior;
  float transmissionRoughness;
  int textureMask;
  int padding1;
  vec4 textureTransforms[6];
} material;

layout(set = 2, binding = 1) uniform sampler2D colorTexture;

struct PointLight { vec4 position; vec4 emission; };
struct DirectionalLight { vec4 direction; vec4 emission; };
struct SpotLight { vec4 position; vec4 direction; vec4 emission; };

layout(set = 3, binding = 0) uniform SceneBuffer {
  vec4 ambientLight;
  PointLight pointLights[10];
  DirectionalLight directionalLights[3];
  SpotLight spotLights[10];
  SpotLight texturedLights[1];
} scene;

layout(location = 0) in vec4 inViewPosition;
layout(location = 1) in vec3 inViewNormal;
layout(location = 2) in vec2 inUV;
layout(location = 3) in flat uvec4 inSegmentation;

layout(location = 0) out uvec4 outColorDepthSegmentation;

const float INV_PI = 0.3183098861837907;

void main() {
  vec4 albedo = material.baseColor;
  if ((material.textureMask & 1) != 0) {
    vec4 t = material.textureTransforms[0];
    albedo = texture(colorTexture, inUV * t.zw + t.xy);
  }
  albedo.a *= 1.0 - objectData.transparency;
  if (albedo.a == 0.0) {
    discard;
  }
  vec3 p = inViewPosition.xyz / inViewPosition.w;
  vec3 n = normalize(inViewNormal);
  if (dot(n, p) > 0.0) {
    n = -n;  // seen from behind: light the side that faces the camera
  }
  vec3 light = scene.ambientLight.rgb;
  for (int i = 0; i < NUM_DIRECTIONAL_LIGHTS; ++i) {
    vec3 toLight = -normalize(mat3(camera.viewMatrix) * scene.directionalLights[i].direction.xyz);
    light += scene.directionalLights[i].emission.rgb * max(dot(n, toLight), 0.0) * INV_PI;
  }
  for (int i = 0; i < NUM_POINT_LIGHTS; ++i) {
    vec3 toLight = (camera.viewMatrix * vec4(scene.pointLights[i].position.xyz, 1.0)).xyz - p;
    float d2 = max(dot(toLight, toLight), 1e-8);
    light += scene.pointLights[i].emission.rgb * max(dot(n, toLight), 0.0) * inversesqrt(d2) / d2 * INV_PI;
  }
  vec3 color = material.emission.rgb + albedo.rgb * light;
  vec4 rgba = vec4(pow(clamp(color, 0.0, 1.0), vec3(1.0 / 2.2)), clamp(albedo.a, 0.0, 1.0));
  outColorDepthSegmentation = uvec4(packUnorm4x8(rgba), floatBitsToUint(-p.z), inSegmentation.y, inSegmentation.x);
}
