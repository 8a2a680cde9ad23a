"""A DAM as one self-contained GLSL function (GLSL ES 3.00 / GLSL 3.30 and later).

``vec3 dam_eval(vec3 view_dir_world, vec3 normal_world)`` returns linear radiance in the
capture's units. Weights are embedded as ``const float`` arrays, layer by layer, (out, in)
row-major (a separable DAM's structural zeros written out), so the function is evaluated
exactly like :func:`damcap.appearance.dam.dam_forward` up to float rounding.
"""

from __future__ import annotations

import numpy as np

from damcap.appearance.dam import LN2, DeepAppearanceMap, split_weights


def _floats(values: np.ndarray) -> str:
    return ",".join(_lit(v) for v in values)


def _lit(x: float) -> str:
    s = f"{float(x):.9g}"
    return s if any(c in s for c in ".e") else s + ".0"


def glsl_source(model: DeepAppearanceMap, prefix: str = "dam") -> str:
    """GLSL source defining ``vec3 {prefix}_eval(vec3 V, vec3 N)``.

    Args:
        model: the DAM.
        prefix: name prefix of every symbol (to place several DAMs in one shader).
    """
    arch = model.arch
    layers = split_weights(model.get_flat_weights().cpu()[None], arch)
    lines = [
        f"// damcap deep appearance map: {arch.depth} hidden layers of {arch.width} ({arch.activation}"
        f"{', separable' if arch.separable else ''}), input '{arch.encoding}', {arch.num_weights} weights, "
        f"radiance scale {model.radiance_scale:.9g}",
    ]
    dims = [arch.layer_shapes[0][1]] + [o for o, _ in arch.layer_shapes]
    for li, ((o, i), (w, b)) in enumerate(zip(arch.layer_shapes, layers)):
        lines.append(f"const float {prefix}_W{li}[{o * i}] = float[{o * i}]({_floats(w[0].flatten().double().numpy())});")
        if b is not None:
            lines.append(f"const float {prefix}_B{li}[{o}] = float[{o}]({_floats(b[0].double().numpy())});")
    act = {
        "leaky_relu": "return x > 0.0 ? x : 0.01 * x;",
        "relu": "return max(x, 0.0);",
        "softplus": "return max(x, 0.0) + log(1.0 + exp(-abs(x)));",
        "shifted_softplus": f"return max(x, 0.0) + log(1.0 + exp(-abs(x))) - {LN2!r};",
        "tanh": "float e = exp(-2.0 * abs(x)); return sign(x) * (1.0 - e) / (1.0 + e);",
    }[arch.activation]
    lines.append(f"float {prefix}_act(float x) {{ {act} }}")
    lines.append(f"vec3 {prefix}_eval(vec3 view_dir_world, vec3 normal_world) {{")
    lines.append("  vec3 V = normalize(view_dir_world);")
    lines.append("  vec3 N = normalize(normal_world);")
    lines.append("  vec3 R = 2.0 * dot(N, V) * N - V;")
    comps = {"vn": ["V", "N"], "nr": ["N", "R"], "vnr": ["V", "N", "R"]}[arch.encoding]
    lines.append(f"  float x0[{dims[0]}];")
    for j, c in enumerate(comps):
        for a, axis in enumerate("xyz"):
            lines.append(f"  x0[{3 * j + a}] = {c}.{axis};")
    for li, (o, i) in enumerate(arch.layer_shapes):
        last = li == len(arch.layer_shapes) - 1
        lines.append(f"  float x{li + 1}[{o}];")
        lines.append(f"  for (int r = 0; r < {o}; ++r) {{")
        lines.append(f"    float s = {prefix}_B{li}[r];" if arch.bias else "    float s = 0.0;")
        lines.append(f"    for (int c = 0; c < {i}; ++c) s += {prefix}_W{li}[r * {i} + c] * x{li}[c];")
        lines.append(f"    x{li + 1}[r] = {'max(s, 0.0) + log(1.0 + exp(-abs(s)))' if last else f'{prefix}_act(s)'};")
        lines.append("  }")
    n = len(arch.layer_shapes)
    lines.append(f"  return vec3(x{n}[0], x{n}[1], x{n}[2]) * {_lit(model.radiance_scale)};")
    lines.append("}")
    return "\n".join(lines) + "\n"
