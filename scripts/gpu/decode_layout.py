"""On one GPU, from the repository root, with tests/reference/wheels copied to the host: does
the channels-last 3D layout (NDHWC) speed up the Wan2.2 VAE's convolutions and decode? Times one
3x3x3 convolution at the decoder's three widths in both layouts (cuDNN autotuning off and on),
then DiffSynth's WanVideoVAE38 (random weights, bf16) decoding 21 latents of a 640x480 chunk with
its Conv3d weights contiguous and then channels-last. libtch exposes no memory format, so this
probes the layout on the reference before any C++ shim is written for it.

  python3 -m pip install -q --no-index --no-deps --find-links tests/reference/wheels --target /tmp/site -r tests/reference/requirements.txt
  PYTHONPATH=/tmp/site python3 scripts/gpu/decode_layout.py
"""
import sys, time, torch
sys.path.insert(0, "tests/reference")
import common
import types
dev, dt = "cuda", torch.bfloat16
def timeit(f, n=3, w=2):
    for _ in range(w): f()
    torch.cuda.synchronize(); ts = []
    for _ in range(n):
        t = time.perf_counter(); f(); torch.cuda.synchronize(); ts.append(time.perf_counter() - t)
    return min(ts), sum(ts) / n
# one 3x3x3 conv at the decoder's top resolution
for bench in (False, True):
    torch.backends.cudnn.benchmark = bench
    for c, h, w in ((256, 480, 640), (512, 240, 320), (1024, 60, 80)):
        conv = torch.nn.Conv3d(c, c, 3, padding=(0, 1, 1)).to(dev, dt)
        x = torch.randn(1, c, 6, h, w, device=dev, dtype=dt)
        a = timeit(lambda: conv(x), 5)
        conv_cl = conv.to(memory_format=torch.channels_last_3d); xcl = x.to(memory_format=torch.channels_last_3d)
        b = timeit(lambda: conv_cl(xcl), 5)
        fl = 2 * c * c * 27 * 4 * h * w
        print(f"conv3d {c}ch {h}x{w} T6 benchmark={bench}: NCDHW {a[0]*1e3:.2f} ms ({fl/a[0]/1e12:.0f} TFLOP/s), NDHWC {b[0]*1e3:.2f} ms ({fl/b[0]/1e12:.0f} TFLOP/s)", flush=True)
        del conv, conv_cl, x, xcl
torch.backends.cudnn.benchmark = False
_, vae_mod, _, _ = common.import_diffsynth()
args = types.SimpleNamespace(tiny=False, vae_dim=None, vae_dec_dim=None)
vae, desc = common.build_vae(vae_mod, args, dev, dt, 0)
print(desc, flush=True)
lat = torch.randn(1, 48, 21, 30, 40, device=dev, dtype=dt)
for bench in (False, True):
    torch.backends.cudnn.benchmark = bench
    a = timeit(lambda: vae.single_decode(lat, dev), 2, 1)
    print(f"reference VAE decode 21 latents, benchmark={bench}, NCDHW: {a[0]:.3f} s (mean {a[1]:.3f})", flush=True)
for m in vae.model.modules():
    if isinstance(m, torch.nn.Conv3d):
        m.weight.data = m.weight.data.to(memory_format=torch.channels_last_3d)
latcl = lat.to(memory_format=torch.channels_last_3d)
for bench in (False, True):
    torch.backends.cudnn.benchmark = bench
    a = timeit(lambda: vae.single_decode(latcl, dev), 2, 1)
    print(f"reference VAE decode 21 latents, benchmark={bench}, channels_last_3d weights: {a[0]:.3f} s (mean {a[1]:.3f})", flush=True)
