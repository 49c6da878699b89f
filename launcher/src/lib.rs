//! Starting BWM's processes: [`launch`] runs one process per GPU (or N CPU processes) on this
//! node with torchrun's environment variables and supervises them (restarts, signals, a per-node
//! agent for multi-node runs); [`submit`] writes the Slurm batch script that runs `bwm launch` on
//! every node and submits it. Their argument structs are the `bwm launch` / `bwm submit` flags.

pub mod launch;
pub mod submit;
