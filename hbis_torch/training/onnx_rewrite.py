"""Rewrites of the exported SR graph that onnxruntime runs faster, same function.

The network's depth-to-space (:func:`hbis_torch.training.net.depth_to_space`) is written as
reshape/permute so that the dynamo exporter handles it; it arrives in the graph as
``Reshape (B, C, h, h, H, W) -> Transpose (0, 1, 4, 2, 5, 3) -> Reshape (B, C, hH, hW)``, and
onnxruntime runs that 6-d Transpose about 4-5 times slower than its ``DepthToSpace`` kernel
(1.2 ms against 0.25 ms for 16 x 128^2 channels; 5 % of the h = 4 network at 256^2 before).
ONNX ``DepthToSpace`` in mode ``"CRD"`` is exactly this rearrangement (input channel
``c h^2 + dy h + dx`` goes to output pixel ``(h y + dy, h x + dx)`` of channel c), so
:func:`fuse_depth_to_space` replaces the three nodes with it. Everything else is left as the
exporter wrote it. The export checks parity with torch after the rewrite, at a size other than
the export size (:func:`hbis_torch.training.export.check_parity`, export/check_onnx.py).

The first convolution reads h^2 + 1 channels (the image's phases and the noise map; 17 at h = 4,
50 at h = 7). onnxruntime runs a convolution in its blocked channel layout (NCHWc, blocks of 8 or
16 channels by the CPU's vector width) only where the input channels are a multiple of the block
or fewer than one block, so this one stays in the plain layout. Every tensor after it then does
too where it meets an ``Add``: the residual sums cannot be fused into the convolutions, and each
block's input is reordered into the blocked layout and back. :func:`split_head_conv` writes the
first convolution as two, over the first multiple of 16 channels of the image and over the rest
with the noise map, summed: the same sum in another order (outputs within 5e-7). The profile of
one 278^2 LR tile (h = 4, 2 threads) then loses 4 of its 5 reorders into the blocked layout, 4 of
its 5 out of it, and 4 of its 6 stand-alone ``Add`` nodes (the residual sums, now fused into the
convolutions, as is the sum of the two halves); the h = 4 network takes 41-44 ms against 45-48
ms, the h = 7 one 54-58 ms against 61-64 ms.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

DEPTH_TO_SPACE_PERM = [0, 1, 4, 2, 5, 3]


def _constants(graph: onnx.GraphProto) -> dict[str, np.ndarray]:
    """Values of the initializers and Constant nodes, by tensor name."""
    values = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant":
            for attr in node.attribute:
                if attr.name == "value":
                    values[node.output[0]] = numpy_helper.to_array(attr.t)
    return values


def _splits_channels_by(graph, reshape: onnx.NodeProto, block: int, producers, constants) -> bool:
    """True if ``reshape`` makes (B, C, block, block, H, W) of (B, C block^2, H, W)."""
    if len(reshape.input) < 2:
        return False
    shape = reshape.input[1]
    if shape in constants:  # a static shape
        dims = np.asarray(constants[shape]).ravel()
        return dims.size == 6 and int(dims[2]) == block and int(dims[3]) == block
    concat = producers.get(shape)
    if concat is None or concat.op_type != "Concat" or len(concat.input) != 6:
        return False
    parts = [constants.get(name) for name in concat.input[2:4]]
    return all(p is not None and np.asarray(p).ravel().tolist() == [block] for p in parts)


def remove_dead_nodes(model: onnx.ModelProto) -> int:
    """Drop nodes whose outputs nothing reads, then unused initializers; returns nodes dropped."""
    graph = model.graph
    keep_outputs = {o.name for o in graph.output}
    dropped = 0
    while True:
        used = keep_outputs | {name for node in graph.node for name in node.input}
        dead = [node for node in graph.node if not any(out in used for out in node.output)]
        if not dead:
            break
        for node in dead:
            graph.node.remove(node)
        dropped += len(dead)
    used = {name for node in graph.node for name in node.input} | keep_outputs
    for init in [t for t in graph.initializer if t.name not in used]:
        graph.initializer.remove(init)
    produced = {name for node in graph.node for name in node.output}
    for info in [v for v in graph.value_info if v.name not in produced]:
        graph.value_info.remove(info)
    return dropped


def fuse_depth_to_space(model: onnx.ModelProto, block: int) -> int:
    """Replace each reshape/transpose/reshape depth-to-space by ``block`` with DepthToSpace (CRD).

    The pattern must be exact: a Reshape whose shape splits the channels into
    (C, block, block) (a constant shape, or a Concat of the exporter's dynamic dimensions with
    constant ``block`` entries in places 2 and 3), a Transpose with permutation
    (0, 1, 4, 2, 5, 3) read only by a Reshape back to 4-d, nothing else reading the
    intermediate tensors. Modifies ``model`` in place; returns the number of replacements.

    Parameters
    ----------
    model : onnx.ModelProto
        The exported network (inputs (B, h^2, H, W) and (B, 2h^2, H, W), output (B, 1, hH, hW)).
    block : int
        The depth-to-space block, h of the network.

    Returns
    -------
    int
        Replacements made (0 if the pattern was not found); dead nodes are then dropped.
    """
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    readers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            readers.setdefault(name, []).append(node)
    graph_outputs = {o.name for o in graph.output}
    constants = _constants(graph)
    replaced = 0
    for transpose in [n for n in graph.node if n.op_type == "Transpose"]:
        perm = next((list(a.ints) for a in transpose.attribute if a.name == "perm"), None)
        if perm != DEPTH_TO_SPACE_PERM:
            continue
        split = producers.get(transpose.input[0])
        after = readers.get(transpose.output[0], [])
        if split is None or split.op_type != "Reshape" or len(after) != 1 or after[0].op_type != "Reshape":
            continue
        merge = after[0]
        if len(readers.get(split.output[0], [])) != 1 or {split.output[0], transpose.output[0]} & graph_outputs:
            continue
        if not _splits_channels_by(graph, split, block, producers, constants):
            continue
        fused = helper.make_node("DepthToSpace", [split.input[0]], [merge.output[0]], blocksize=int(block),
                                 mode="CRD", name=f"depth_to_space_{replaced}")
        position = list(graph.node).index(merge)
        graph.node.insert(position, fused)
        for node in (split, transpose, merge):
            graph.node.remove(node)
        replaced += 1
    if replaced:
        remove_dead_nodes(model)
    return replaced


SPLIT_BLOCK = 16  # channels: a multiple of either of onnxruntime's NCHWc blocks (8 with AVX2, 16 with AVX-512)
SPLIT_HEAD_ADD = "head_add"  # the node that sums the split first convolution: the head's output


def split_head_conv(model: onnx.ModelProto, block: int = SPLIT_BLOCK) -> int:
    """Write the first convolution, ``Conv(Concat(image, noise))``, as two convolutions summed.

    ``Conv(image[:, :m]) + Conv(Concat(image[:, m:], noise))``, with m the largest multiple of
    ``block`` not above the image's h^2 channels; the bias goes with the first. Nothing is done
    where the input has fewer than ``block`` + 1 channels (h = 2 and 3: onnxruntime's blocked
    layout takes it as it is). Modifies ``model`` in place; returns 1 if it rewrote, else 0.

    Parameters
    ----------
    model : onnx.ModelProto
        The exported network: a ``Concat`` of the graph inputs ``base`` (after its ``Sub``) and
        ``noise`` along the channels, read only by one ``Conv`` whose output has a shape in the
        graph's ``value_info`` (the exporter's symbolic height and width, which onnxruntime needs to
        prove the residual sums' inputs alike).
    block : int

    Returns
    -------
    int
    """
    graph = model.graph
    cat = next((n for n in graph.node if n.op_type == "Concat" and len(n.input) == 2 and n.input[1] == "noise"), None)
    conv = [n for n in graph.node if cat.output[0] in n.input] if cat is not None else []
    if len(conv) != 1 or conv[0].op_type != "Conv" or len(conv[0].input) != 3:
        return 0
    conv = conv[0]
    initializers = {t.name: t for t in graph.initializer}
    shapes = {v.name: v for v in graph.value_info}
    if conv.input[1] not in initializers or conv.output[0] not in shapes:
        return 0
    weight = numpy_helper.to_array(initializers[conv.input[1]])
    channels = weight.shape[1] - 1  # the image's; the last is the noise map
    main = channels - channels % block
    if main == 0:
        return 0

    def shaped(name: str, count: int) -> None:  # the head output's symbolic shape, with count channels
        info = onnx.ValueInfoProto()
        info.CopyFrom(shapes[conv.output[0]])
        info.name = name
        info.type.tensor_type.shape.dim[1].dim_value = count
        graph.value_info.append(info)

    image, noise = cat.input
    nodes = []
    if channels > main:
        sizes = numpy_helper.from_array(np.array([main, channels - main], np.int64), "head.split")
        graph.initializer.append(sizes)
        nodes += [helper.make_node("Split", [image, sizes.name], ["head_image", "head_image_rest"], axis=1,
                                   name="head_split"),
                  helper.make_node("Concat", ["head_image_rest", noise], ["head_rest_in"], axis=1, name="head_concat")]
        for name, count in (("head_image", main), ("head_image_rest", channels - main),
                            ("head_rest_in", channels - main + 1)):
            shaped(name, count)
        image, rest_in = "head_image", "head_rest_in"
    else:
        rest_in = noise
    weights = [numpy_helper.from_array(np.ascontiguousarray(w), name) for w, name in
               ((weight[:, :main], "head.weight.image"), (weight[:, main:], "head.weight.rest"))]
    graph.initializer.extend(weights)
    main_conv = helper.make_node("Conv", [image, weights[0].name, conv.input[2]], ["head_main"], name="head_main")
    rest_conv = helper.make_node("Conv", [rest_in, weights[1].name], ["head_rest"], name="head_rest")
    for node in (main_conv, rest_conv):
        node.attribute.extend(conv.attribute)
        shaped(node.output[0], weight.shape[0])
    nodes += [main_conv, rest_conv, helper.make_node("Add", ["head_main", "head_rest"], [conv.output[0]],
                                                     name=SPLIT_HEAD_ADD)]
    position = list(graph.node).index(cat)
    for offset, node in enumerate(nodes):
        graph.node.insert(position + offset, node)
    graph.node.remove(conv)
    graph.node.remove(cat)
    graph.initializer.remove(initializers[conv.input[1]])
    return 1
