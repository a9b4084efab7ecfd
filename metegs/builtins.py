"""Registration of metegs' built-in components (as lazy "module:attribute" strings: nothing is imported here)."""

from metegs.registry import registry

# One registration per line, a table to read down.
# fmt: off
_parsers = registry("parser")
_parsers.register("colmap", "metegs.data.parsers.colmap:ColmapParser", description="COLMAP sparse model (binary or text), through pycolmap")
_parsers.register("nerfstudio", "metegs.data.parsers.nerfstudio:NerfstudioParser", description="nerfstudio transforms.json")
_parsers.register("llff", "metegs.data.parsers.llff:LLFFParser", description="LLFF poses_bounds.npy + images*/")
_parsers.register("blender", "metegs.data.parsers.blender:BlenderParser", description="Blender/NeRF-synthetic transforms_{train,val,test}.json")
_parsers.register("synthetic", "metegs.data.parsers.synthetic:SyntheticParser", description="procedural ray-cast scene in metres (the default)")

_raster = registry("rasterizer")
_raster.register("torch", "metegs.render.torch_backend:TorchRasterizer", description="vectorised PyTorch reference (any device)")
_raster.register("cpu", "metegs.render.cpu_backend:CpuRasterizer", description="compiled C++ tile compositing (CPU only; built on first use)")
_raster.register("gsplat", "metegs.render.gsplat_backend:GsplatRasterizer", description="gsplat CUDA kernels (CUDA devices only; pip install 'metegs[cuda]')")

_weather = registry("weather")
_weather.register("rain-streaks", "metegs.weather.rain_streaks:RainStreaksConfig", description="per-view rain streak Gaussians from θ_rain")
_weather.register("fog-gaussians", "metegs.weather.fog_gaussians:FogGaussiansConfig", description="fog as a static lattice of Gaussians (exp(-βd))")
_weather.register("fog-analytic", "metegs.weather.fog_analytic:FogAnalyticConfig", description="fog from rendered depth: C·t + A(1-α·t)")
_weather.register("lens-droplets", "metegs.weather.lens_droplets:LensDropletsConfig", description="refractive drops on the lens (image space)")

_methods = registry("method")
_methods.register("3dgs", "metegs.methods:gaussian_splatting", description="plain 3D Gaussian Splatting (0.8·L1 + 0.2·D-SSIM)")
_methods.register("metegs-full", "metegs.methods:metegs_full", description="MeteGS: rain + fog weather branch, GTN, clean branch, depth pruning, extra points")
_methods.register("metegs-rain", "metegs.methods:metegs_rain", description="MeteGS with rain streaks only")
_methods.register("metegs-fog", "metegs.methods:metegs_fog", description="MeteGS with analytic fog only")

_readers = registry("meteo_reader")
_readers.register("csv", "metegs.meteo.readers.csv_reader:CsvReader", description="any delimited table of station records, described by options (columns, units, time zone)")
_readers.register("metar", "metegs.meteo.readers.metar_reader:MetarReader", description="METAR/SPECI reports, bulletins and collectives (P/6/7 precipitation groups)")
_readers.register("ghcnh", "metegs.meteo.readers.ghcnh_reader:GhcnhReader", description="NOAA GHCNh hourly pipe-separated .psv")
_readers.register("isd", "metegs.meteo.readers.isd_reader:IsdReader", description="NOAA ISD full format (DS3505): visibility, AA liquid precipitation, MW present weather")
_readers.register("open-meteo", "metegs.meteo.readers.open_meteo_reader:OpenMeteoReader", description="Open-Meteo hourly JSON (precipitation, visibility, wind)")

_restorers = registry("restorer")
_restorers.register("dcp", "metegs.restore.dehaze:DarkChannelPriorConfig", description="dark channel prior dehazing, guided-filter transmission refinement (He et al. 2009/2011)")
_restorers.register("kang2012", "metegs.restore.derain:KangDerainConfig", description="rain-streak removal by bilateral decomposition, dictionary learning and HOG clustering (Kang et al. 2012)")
_restorers.register("restormer", "metegs.restore.learned:RestormerConfig", description="Restormer deraining from user-given weights (Zamir et al. 2022)")
_restorers.register("dehazeformer", "metegs.restore.learned:DehazeFormerConfig", description="DehazeFormer dehazing from user-given weights (Song et al. 2023)")
# fmt: on
