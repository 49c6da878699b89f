//! A job of one process: every collective is the identity (with the same argument checks as the
//! other back ends, so code that is wrong for N ranks fails on one too).

use super::{check_reducible, check_root, check_split, Collective};
use anyhow::Result;
use tch::Tensor;

#[derive(Debug, Default)]
pub struct LocalCollective;

impl LocalCollective {
    pub fn new() -> Self {
        Self
    }
}

fn copy_flat(src: &Tensor, dst: &mut Tensor) -> Result<()> {
    let flat = src.f_reshape(dst.size())?;
    tch::no_grad(|| dst.f_copy_(&flat))?;
    Ok(())
}

impl Collective for LocalCollective {
    fn rank(&self) -> usize {
        0
    }

    fn world_size(&self) -> usize {
        1
    }

    fn all_reduce_sum(&mut self, tensor: &mut Tensor) -> Result<()> {
        check_reducible(tensor.f_kind()?, false, "all_reduce_sum")
    }

    fn all_reduce_mean(&mut self, tensor: &mut Tensor) -> Result<()> {
        check_reducible(tensor.f_kind()?, true, "all_reduce_mean")
    }

    fn reduce_scatter_sum(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        check_split("reduce_scatter_sum", input, output, 1)?;
        check_reducible(input.f_kind()?, false, "reduce_scatter_sum")?;
        copy_flat(input, output)
    }

    fn all_gather(&mut self, input: &Tensor, output: &mut Tensor) -> Result<()> {
        check_split("all_gather", output, input, 1)?;
        copy_flat(input, output)
    }

    fn start_reduce_sum(&mut self, tensor: &Tensor, root: Option<usize>) -> Result<()> {
        if let Some(r) = root {
            check_root("start_reduce_sum", r, 1)?;
        }
        check_reducible(tensor.f_kind()?, false, "start_reduce_sum")
    }

    fn broadcast(&mut self, _tensor: &mut Tensor, root: usize) -> Result<()> {
        check_root("broadcast", root, 1)
    }

    fn barrier(&mut self) -> Result<()> {
        Ok(())
    }
}
