//! Opening the GPU: [`GpuDevice`], the adapter and device that both the training kernels
//! ([`ComputeDevice`]) and the renderer ([`crate::GpuContext`]) hold, opened one way (the
//! adapter [`AdapterPolicy`] picks, its own buffer limits, the optional features it has) and
//! checked one way ([`GpuDevice::check_storage`], [`GpuDevice::check_state`]).
//!
//! [`ComputeDevice`] adds what the training kernels need: f32 storage buffers, dispatches of `n`
//! invocations, batches of dispatches, read-back, with native f32 atomics where the adapter has
//! them.

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use crate::hashgrid::AtomicMode;
use crate::layout::{dispatch_size, WORKGROUP};
use crate::render::{check_state, pick_adapter, watch, DeviceState};
use crate::{AdapterPolicy, GpuError};

/// An open adapter and device: the queue, what the adapter is, the limits and features the
/// device was opened with, and the device's asynchronous errors.
pub struct GpuDevice {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) info: wgpu::AdapterInfo,
    pub(crate) limits: wgpu::Limits,
    pub(crate) features: wgpu::Features,
    pub(crate) state: Arc<Mutex<DeviceState>>,
}

impl std::fmt::Debug for GpuDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuDevice({})", self.adapter_name())
    }
}

impl GpuDevice {
    /// Opens `adapter` with its own buffer limits (models and frames can be large; WebGPU's
    /// defaults otherwise, as the kernels use nothing beyond them) and those of `optional`
    /// features it has.
    pub(crate) fn open(
        adapter: wgpu::Adapter,
        label: &str,
        optional: wgpu::Features,
    ) -> Result<Self, GpuError> {
        let info = adapter.get_info();
        let al = adapter.limits();
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: al.max_storage_buffer_binding_size,
            max_buffer_size: al.max_buffer_size,
            ..wgpu::Limits::default()
        };
        let features = adapter.features() & optional;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some(label),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: format!("{} ({:?})", info.name, info.backend),
            error: e.to_string(),
        })?;
        let state = watch(&device);
        Ok(GpuDevice {
            device,
            queue,
            info,
            limits,
            features,
            state,
        })
    }

    /// `name (backend, device type)` of the adapter in use.
    pub fn adapter_name(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }

    /// Checks that a storage buffer of `bytes` fits the device's limits (naming the limit).
    pub fn check_storage(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let l = &self.limits;
        for (limit, max) in [
            (
                "max_storage_buffer_binding_size",
                l.max_storage_buffer_binding_size,
            ),
            ("max_buffer_size", l.max_buffer_size),
        ] {
            if bytes > max {
                return Err(GpuError::Limit {
                    what: what.to_string(),
                    amount: bytes,
                    unit: "bytes",
                    limit,
                    max,
                });
            }
        }
        Ok(())
    }

    /// Fails with what the device reported since the last check (lost device, validation).
    pub(crate) fn check_state(&self) -> Result<(), GpuError> {
        check_state(&self.state)
    }
}

/// An open device for compute kernels.
pub struct ComputeDevice {
    gpu: GpuDevice,
    /// While a batch is open ([`ComputeDevice::begin_batch`]): the encoder that dispatches and
    /// clears are recorded into instead of being submitted one by one.
    batch: Mutex<Option<wgpu::CommandEncoder>>,
}

impl std::ops::Deref for ComputeDevice {
    type Target = GpuDevice;

    fn deref(&self) -> &GpuDevice {
        &self.gpu
    }
}

impl std::fmt::Debug for ComputeDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ComputeDevice({})", self.adapter_name())
    }
}

impl ComputeDevice {
    /// Opens the best adapter `policy` allows, with native f32 atomics enabled when the adapter
    /// offers them (`wgpu::Features::SHADER_FLOAT32_ATOMIC`).
    pub fn open(policy: AdapterPolicy) -> Result<Self, GpuError> {
        let gpu = GpuDevice::open(
            pick_adapter(policy)?,
            "msth compute",
            wgpu::Features::SHADER_FLOAT32_ATOMIC,
        )?;
        Ok(ComputeDevice {
            gpu,
            batch: Mutex::new(None),
        })
    }

    /// Whether native f32 atomics (`atomic<f32>`, `atomicAdd`) are enabled on this device.
    pub fn has_float_atomics(&self) -> bool {
        self.features
            .contains(wgpu::Features::SHADER_FLOAT32_ATOMIC)
    }

    /// A storage buffer holding `data` (at least one word), readable back and writable.
    pub fn buffer_f32(&self, what: &str, data: &[f32]) -> Result<wgpu::Buffer, GpuError> {
        let bytes: &[u8] = if data.is_empty() {
            &[0; 4]
        } else {
            bytemuck::cast_slice(data)
        };
        self.check_storage(what, bytes.len() as u64)?;
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents: bytes,
                usage: Self::usage(),
            }))
    }

    /// A zeroed storage buffer of `n` f32 (at least one).
    pub fn zeros_f32(&self, what: &str, n: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (n.max(1) as u64).saturating_mul(4);
        self.check_storage(what, bytes)?;
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: bytes,
            usage: Self::usage(),
            mapped_at_creation: false,
        }))
    }

    fn usage() -> wgpu::BufferUsages {
        wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST
    }

    /// Writes `data` at the start of `buf`.
    pub fn write_f32(&self, buf: &wgpu::Buffer, data: &[f32]) -> Result<(), GpuError> {
        if (data.len() as u64) * 4 > buf.size() {
            return Err(GpuError::Input(format!(
                "{} values do not fit a buffer of {} bytes",
                data.len(),
                buf.size()
            )));
        }
        if !data.is_empty() {
            // A write lands before every command submitted after it: submit what a batch has
            // recorded so far, so the write also lands after those.
            self.flush()?;
            self.queue.write_buffer(buf, 0, bytemuck::cast_slice(data));
        }
        Ok(())
    }

    /// Sets every byte of `buf` to zero (a gradient buffer before a backward pass).
    pub fn clear(&self, buf: &wgpu::Buffer) -> Result<(), GpuError> {
        if let Some(enc) = self.recording().as_mut() {
            enc.clear_buffer(buf, 0, None);
            return Ok(());
        }
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        enc.clear_buffer(buf, 0, None);
        self.queue.submit([enc.finish()]);
        self.wait()?;
        check_state(&self.state)
    }

    /// Reads the first `n` f32 of `buf` back.
    pub fn read_f32(&self, buf: &wgpu::Buffer, n: usize) -> Result<Vec<f32>, GpuError> {
        self.flush()?;
        if n == 0 {
            return Ok(Vec::new());
        }
        let bytes = n as u64 * 4;
        if bytes > buf.size() {
            return Err(GpuError::Input(format!(
                "reading {n} values from a buffer of {} bytes",
                buf.size()
            )));
        }
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        enc.copy_buffer_to_buffer(buf, 0, &staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        match rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Backend(format!("reading results back: {e}"))),
            Err(_) => return Err(GpuError::Backend("reading results back: no answer".into())),
        }
        check_state(&self.state)?;
        let out = {
            let view = staging
                .get_mapped_range(..)
                .map_err(|e| GpuError::Backend(format!("reading results back: {e}")))?;
            bytemuck::cast_slice::<u8, f32>(&view).to_vec()
        };
        staging.unmap();
        Ok(out)
    }

    /// Compiles `source` (entry point `entry`) against `layout`; shader errors are
    /// [`GpuError::Shader`].
    pub(crate) fn pipeline(
        &self,
        label: &str,
        source: &str,
        entry: &str,
        layout: &wgpu::BindGroupLayout,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pl = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(layout)],
                immediate_size: 0,
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(format!("{label}: {e}")));
        }
        Ok(pipeline)
    }

    /// A bind group layout of one uniform (binding 0) followed by storage buffers, `true` for
    /// read-only.
    pub(crate) fn bind_layout(&self, label: &str, storage: &[bool]) -> wgpu::BindGroupLayout {
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        for (i, &read_only) in storage.iter().enumerate() {
            entries.push(wgpu::BindGroupLayoutEntry {
                binding: i as u32 + 1,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            });
        }
        self.device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries: &entries,
            })
    }

    /// Runs `pipeline` for `invocations` invocations (64-wide workgroups, tiled into 2D when
    /// one dimension is not enough) with `uniform` at binding 0 and `buffers` from binding 1,
    /// and waits for it.
    pub(crate) fn run(
        &self,
        pipeline: &wgpu::ComputePipeline,
        layout: &wgpu::BindGroupLayout,
        uniform: &[u8],
        buffers: &[&wgpu::Buffer],
        invocations: u64,
    ) -> Result<(), GpuError> {
        if invocations == 0 {
            return Ok(());
        }
        let max = self.limits.max_compute_workgroups_per_dimension;
        let too_many = || GpuError::Limit {
            what: format!("a dispatch of {invocations} invocations"),
            amount: invocations,
            unit: "invocations",
            limit: "max_compute_workgroups_per_dimension (squared, times 64)",
            max: max as u64 * max as u64 * WORKGROUP as u64,
        };
        let count = u32::try_from(invocations).map_err(|_| too_many())?;
        let (gx, gy) = dispatch_size(count, max).ok_or_else(too_many)?;
        let ubuf = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("kernel parameters"),
                contents: uniform,
                usage: wgpu::BufferUsages::UNIFORM,
            });
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: ubuf.as_entire_binding(),
        }];
        for (i, b) in buffers.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: i as u32 + 1,
                resource: b.as_entire_binding(),
            });
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout,
            entries: &entries,
        });
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        };
        if let Some(enc) = self.recording().as_mut() {
            record(enc);
            return match pollster::block_on(scope.pop()) {
                Some(e) => Err(GpuError::Backend(e.to_string())),
                None => Ok(()),
            };
        }
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        record(&mut enc);
        self.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        self.wait()?;
        check_state(&self.state)
    }

    fn recording(&self) -> std::sync::MutexGuard<'_, Option<wgpu::CommandEncoder>> {
        self.batch.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records the dispatches and clears that follow into one command encoder, submitted at
    /// [`ComputeDevice::end_batch`] (or before a read or write that needs it): one submission
    /// and no waits between kernels, where each call alone submits and waits (right for tests,
    /// the per-operation synchronisation trap for a training step). Batches do not nest: a
    /// second begin submits the first.
    pub fn begin_batch(&self) -> Result<(), GpuError> {
        self.flush()?;
        *self.recording() = Some(self.device.create_command_encoder(
            &wgpu::CommandEncoderDescriptor {
                label: Some("batch"),
            },
        ));
        Ok(())
    }

    /// Submits what the open batch recorded, waits for it, and closes the batch.
    pub fn end_batch(&self) -> Result<(), GpuError> {
        self.flush()?;
        *self.recording() = None;
        Ok(())
    }

    /// Submits what the open batch has recorded so far and waits for it; the batch stays open
    /// (recording into a fresh encoder). Nothing to do without a batch.
    fn flush(&self) -> Result<(), GpuError> {
        let enc = {
            let mut rec = self.recording();
            match rec.as_mut() {
                None => return Ok(()),
                Some(enc) => std::mem::replace(
                    enc,
                    self.device
                        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                            label: Some("batch"),
                        }),
                ),
            }
        };
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        self.wait()?;
        check_state(&self.state)
    }

    fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Backend(format!("waiting for the device: {e}")))
    }
}

/// A forward kernel and its backward, compiled for one device over one bind layout (uniform at
/// binding 0, then two read-only storage buffers and one read-write): the shape every training
/// kernel of this crate has. The backward's gradient additions use `mode`.
pub(crate) struct KernelPair {
    layout: wgpu::BindGroupLayout,
    forward: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    pub(crate) mode: AtomicMode,
}

/// The WGSL and entry points of a [`KernelPair`]: `common` is prepended to both, and the
/// backward gets the `add_grad` of its [`AtomicMode`] between `common` and its own source.
pub(crate) struct PairSource<'a> {
    pub label: &'a str,
    pub common: &'a str,
    pub forward: (&'a str, &'a str),
    pub backward: (&'a str, &'a str),
}

impl KernelPair {
    /// Compiles both kernels; [`AtomicMode::NativeF32`] on a device without f32 atomics is a
    /// [`GpuError::MissingFeature`].
    pub(crate) fn new(
        dev: &ComputeDevice,
        mode: AtomicMode,
        src: PairSource,
    ) -> Result<Self, GpuError> {
        if mode == AtomicMode::NativeF32 && !dev.has_float_atomics() {
            return Err(GpuError::MissingFeature(format!(
                "{} has no f32 atomics (wgpu::Features::SHADER_FLOAT32_ATOMIC)",
                dev.adapter_name()
            )));
        }
        let layout = dev.bind_layout(src.label, &[true, true, false]);
        let (fwd_wgsl, fwd_entry) = src.forward;
        let (bwd_wgsl, bwd_entry) = src.backward;
        let forward = dev.pipeline(
            &format!("{} forward", src.label),
            &format!("{}\n{fwd_wgsl}", src.common),
            fwd_entry,
            &layout,
        )?;
        let backward = dev.pipeline(
            &format!("{} backward", src.label),
            &format!("{}\n{}\n{bwd_wgsl}", src.common, mode.wgsl()),
            bwd_entry,
            &layout,
        )?;
        Ok(KernelPair {
            layout,
            forward,
            backward,
            mode,
        })
    }

    /// Runs the forward (`backward: false`) or the backward over `invocations` invocations with
    /// `uniform` at binding 0 and `buffers` at bindings 1-3.
    pub(crate) fn run(
        &self,
        dev: &ComputeDevice,
        backward: bool,
        uniform: &[u8],
        buffers: &[&wgpu::Buffer; 3],
        invocations: u64,
    ) -> Result<(), GpuError> {
        let pipeline = if backward {
            &self.backward
        } else {
            &self.forward
        };
        dev.run(pipeline, &self.layout, uniform, buffers, invocations)
    }
}
