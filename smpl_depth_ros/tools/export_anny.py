"""Write the shipped anny model data (run once by maintainers; output is committed).

    python -m smpl_depth_ros.tools.export_anny [--out smpl_depth_ros/data]

Builds anny (first construction ~100-130 s, cached under ~/.cache/anny), saves its
compact ModelData as safetensors and the adult shape statistics (mean/std of 4,000
phenotype samples from anny's SimpleShapeDistribution, ages 18-80, seed 0) as JSON.
"""
import argparse
import json
import os

import torch


def main(argv=None):
    import anny
    from anny.shape_distribution import SimpleShapeDistribution

    from smpl_depth_ros.body.anny_model import DATA_NAME, RIG, TOPOLOGY

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--out', default=os.path.join(os.path.dirname(__file__), '..', 'data'))
    args = ap.parse_args(argv)
    m = anny.Anny(rig=RIG, topology=TOPOLOGY, skinning_method='lbs')
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, DATA_NAME + '.safetensors')
    m.to_model_data().save_safetensors(path)
    torch.manual_seed(0)
    dist = SimpleShapeDistribution(m, morphological_age_distribution=torch.distributions.Uniform(
        torch.tensor(18.0, dtype=m.dtype), torch.tensor(80.0, dtype=m.dtype)))
    _, ph = dist.sample(4000)
    s = torch.stack([ph[k] for k in m.phenotype_labels], -1).double().clamp(0, 1)
    meta = dict(rig=RIG, topology=TOPOLOGY, anny_version=anny.__version__,
                shape_names=list(m.phenotype_labels),
                shape_mean=s.mean(0).tolist(), shape_std=s.std(0).tolist(),
                shape_min=s.min(0).values.tolist(), shape_max=s.max(0).values.tolist())
    with open(path.replace('.safetensors', '.json'), 'w') as f:
        json.dump(meta, f, indent=1)
    print(json.dumps(meta, indent=1))


if __name__ == '__main__':
    main()
