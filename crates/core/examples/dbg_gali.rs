use salient_core::orbit::{integrate, OrbitConfig, Requests};
use salient_core::{section::on_section, HenonHeiles, Scheme, TangentMap};
fn main() {
    let ham = HenonHeiles;
    let args: Vec<f64> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    let map = TangentMap::new(&ham, &Scheme::by_name("sbab2c").unwrap(), 0.05);
    let (q, p) = on_section(&ham, 0.125, &[args[0]], &[args[1]]).unwrap();
    let req = Requests {
        gali: true,
        samples_per_decade: 4,
        ..Requests::default()
    };
    let mut cfg = OrbitConfig::new(0.05, args[2]);
    if args.len() > 3 {
        cfg.deviation = salient_core::Deviation::Random {
            seed: args[3] as u64,
        };
    }
    let r = integrate::<_, 2, 4>(&map, q, p, &cfg, &req);
    for s in &r.series {
        println!(
            "{:10.1} sali {:.3e} g2 {:.3e} g3 {:.3e} g4 {:.3e} mle {:.3e}",
            s.t, s.sali, s.gali[0], s.gali[1], s.gali[2], s.mle
        );
    }
}
